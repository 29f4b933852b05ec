"""sim stage of tsnav (see docs/ARCHITECTURE.md)."""
