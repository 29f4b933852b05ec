"""Evaluation: the batched runner and its policies (random, oracle, explorer, trained agent), episode outcomes,
checkpoint selection and ``tsnav eval``."""
