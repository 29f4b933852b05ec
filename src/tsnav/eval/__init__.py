"""eval stage of tsnav (see docs/ARCHITECTURE.md)."""
