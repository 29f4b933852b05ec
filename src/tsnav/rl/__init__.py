"""Agent training: the A3C and batched trainers, rollouts and loss, checkpoints, run logs (docs/ARCHITECTURE.md)."""
