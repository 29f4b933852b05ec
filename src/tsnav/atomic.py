"""Atomic writes: a temporary file (or folder) in the same folder, then ``os.replace``.

Readers never see a half-written file, and an interrupted write leaves the previous version in place. Every
temp-file-and-rename in tsnav goes through here: bytes, text and JSON directly; files that a library writes
by path (HDF5, ``.npz``) through :func:`atomic_path`; folders through :func:`atomic_folder`.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


def _umask() -> int:
    """The process's umask, read without changing it where Linux tells it (``/proc/self/status``); elsewhere set
    and restored at once."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode(path: str | Path | None = None) -> int:
    """The mode a plain ``open(path, "w")`` would leave ``path`` with: an existing file's own, else 0o666 less the
    umask. The temp files of :func:`tempfile.mkstemp` are 0o600, which a rename would otherwise carry over."""
    if path is not None:
        try:
            return os.stat(path).st_mode & 0o7777
        except OSError:
            pass
    return 0o666 & ~_umask()


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temp file in the same folder and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj, indent: int | None = 1, sort_keys: bool = True) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=sort_keys) + "\n")


def atomic_save_figure(fig, path: str | Path, **savefig_kwargs) -> Path:
    """Render a matplotlib figure (format from the suffix, PNG by default) and write it atomically; returns
    the path. A killed report or plot never leaves a truncated picture behind."""
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=path.suffix.lstrip(".") or "png", **savefig_kwargs)
    atomic_write_bytes(path, buf.getvalue())
    return path


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a hidden temporary path next to ``path`` for a writer that needs a file name (``h5py.File(tmp,
    "w")``, ``open(tmp, "wb")``); when the block ends without error the file is renamed to ``path``, on any
    error (or interruption) it is removed and ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        if tmp.exists():
            os.chmod(tmp, file_mode(path))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_folder(final: str | Path) -> Iterator[Path]:
    """Yield an empty hidden temporary folder ``.<name>.partial-<pid>`` next to ``final``; when the block ends
    without error an existing ``final`` is removed and the folder renamed to it; on any error (or
    interruption) the temporary folder is removed."""
    final = Path(final)
    tmp = final.parent / f".{final.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
