"""tsnav: object navigation with the Two-Stage Reward Mechanism (TSRM) and Depth-Enhanced MAE (DE-MAE)."""

__version__ = "0.1.0"
