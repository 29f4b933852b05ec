"""Errors shared by every stage (the lowest layer: imports nothing of tsnav)."""

from __future__ import annotations

from dataclasses import fields
from typing import TypeVar

T = TypeVar("T")


class CommandError(Exception):
    """An error the user can fix; the ``tsnav`` command prints it as one line without a traceback."""


def from_fields(cls: type[T], d: dict, what: str) -> T:
    """``cls(**d)`` for a dataclass ``cls``, refusing keys that are none of its fields with a ``ValueError``
    naming them (``what``: e.g. "training config"), as when a file was written by another version."""
    unknown = set(d) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown {what} field(s): {', '.join(sorted(unknown))}")
    return cls(**d)


def read_json(path, error: type[Exception] = CommandError, missing: str | None = None):
    """The JSON document in file ``path``. A file that cannot be read or is not valid JSON raises ``error`` in one
    line naming the file and the problem (with its line and column); a missing file does so when ``missing``
    says how (e.g. "missing file"), else FileNotFoundError passes through."""
    import json

    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        if missing is None:
            raise
        raise error(f"{path}: {missing}") from None
    except json.JSONDecodeError as e:
        raise error(f"{path}: not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise error(f"{path}: cannot read: {e}") from None
