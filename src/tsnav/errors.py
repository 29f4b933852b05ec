"""Errors shared by every stage (the lowest layer: imports nothing of tsnav)."""

from __future__ import annotations


class CommandError(Exception):
    """An error the user can fix; the ``tsnav`` command prints it as one line without a traceback."""
