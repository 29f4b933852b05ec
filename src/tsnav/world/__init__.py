"""Worlds: the real iTHOR rooms from their recorded layouts and procedural houses, navigation grids, builds, fidelity."""
