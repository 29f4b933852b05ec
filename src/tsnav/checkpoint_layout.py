"""The checkpoint folder layout and its JSON files, without torch (docs/ARCHITECTURE.md "Checkpoints and
resume"): names, listing, pruning, setting broken checkpoints aside, reading ``state.json`` and a run's progress.

:mod:`tsnav.checkpoint` adds the tensor files (safetensors) and re-exports all of this; readers that only
look at progress (the report, the demo's stage table) import this module and need no torch::

    checkpoints/ckpt_<step, 9 digits>/   model.safetensors, optimizer.safetensors, state.json (rng_rank<r>.json)
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path


class BrokenCheckpoint(ValueError):
    """A checkpoint file that cannot be read; the message names the file and says what is wrong in one line."""


def _one_line(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def read_json(path: str | Path) -> dict:
    """A checkpoint's JSON file; :class:`BrokenCheckpoint` when it is missing, truncated or not an object."""
    try:
        with open(path) as f:
            obj = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BrokenCheckpoint(f"{path}: broken checkpoint file ({_one_line(e)})") from None
    if not isinstance(obj, dict):
        raise BrokenCheckpoint(f"{path}: broken checkpoint file (not a JSON object)")
    return obj


#: Folder (inside a run or detector folder) holding one sub-folder per checkpoint.
CHECKPOINTS = "checkpoints"
MODEL_FILE = "model.safetensors"
OPTIMIZER_FILE = "optimizer.safetensors"
#: Earlier name of the optimizer file (agent checkpoints before the layouts were unified); still read.
OLD_OPTIMIZER_FILE = "optim.safetensors"
STATE_FILE = "state.json"
_COMPLETE = re.compile(r"^ckpt_\d+$")


def checkpoint_name(step: int) -> str:
    """Folder name of the checkpoint of ``step`` (``ckpt_<step, 9 digits>``; sorts by step)."""
    return f"ckpt_{int(step):09d}"


def checkpoint_step(path: str | Path) -> int:
    """The step of a checkpoint folder from its name."""
    return int(Path(path).name.split("_", 1)[1].split(".")[0])


def list_checkpoints(folder: str | Path) -> list[Path]:
    """Complete checkpoint folders (``ckpt_<step>/`` with a ``state.json``) of a checkpoints folder, oldest
    first. Temporary (``.ckpt_*``) and set-aside (``*.broken``) folders are not listed."""
    d = Path(folder)
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if p.is_dir() and _COMPLETE.match(p.name) and (p / STATE_FILE).exists())


def optimizer_file(ckpt: str | Path) -> Path:
    """The optimizer file of a checkpoint folder: ``optimizer.safetensors``, or the older
    ``optim.safetensors`` when only that exists."""
    ckpt = Path(ckpt)
    new = ckpt / OPTIMIZER_FILE
    return ckpt / OLD_OPTIMIZER_FILE if not new.exists() and (ckpt / OLD_OPTIMIZER_FILE).exists() else new


def checkpoint_tmp_path(folder: str | Path, step: int) -> Path:
    """Path of the temporary folder ``.ckpt_<step>.tmp`` of a checkpoint (see :func:`checkpoint_tmp`)."""
    return Path(folder) / f".{checkpoint_name(step)}.tmp"


def checkpoint_tmp(folder: str | Path, step: int) -> Path:
    """Create (empty) the temporary folder ``.ckpt_<step>.tmp`` of a checkpoint; :func:`commit_checkpoint`
    renames it when complete (writers that fill it from several processes, e.g. one RNG file per rank)."""
    tmp = checkpoint_tmp_path(folder, step)
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    return tmp


def commit_checkpoint(
    folder: str | Path, tmp: str | Path, step: int, keep: int = 2, milestone_every: int | None = None
) -> Path:
    """Rename the complete temporary folder ``tmp`` to ``folder/ckpt_<step>`` and remove older checkpoints
    beyond the ``keep`` newest, except those whose step is a multiple of ``milestone_every``."""
    final = Path(folder) / checkpoint_name(step)
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)
    prune_checkpoints(folder, keep, milestone_every)
    return final


def prune_checkpoints(folder: str | Path, keep: int = 2, milestone_every: int | None = None) -> None:
    """Remove the checkpoints of ``folder`` older than the ``keep`` newest, except milestones (step a multiple
    of ``milestone_every``)."""
    for old in list_checkpoints(folder)[:-keep]:
        if milestone_every and checkpoint_step(old) % milestone_every == 0:
            continue
        shutil.rmtree(old, ignore_errors=True)


def set_aside(path: str | Path) -> None:
    """Rename a broken checkpoint folder to ``<name>.broken`` (kept for inspection, no longer listed)."""
    path = Path(path)
    dest = path.with_name(path.name + ".broken")
    if dest.exists():
        shutil.rmtree(dest)
    os.replace(path, dest)


def newest_state(folder: str | Path) -> dict | None:
    """``state.json`` of the newest checkpoint of ``folder`` whose state reads (a reader: sets nothing aside,
    prints nothing); None when there is none."""
    for p in list_checkpoints(folder)[::-1]:
        try:
            return read_json(p / STATE_FILE)
        except BrokenCheckpoint:
            continue
    return None


#: File of the pretraining run folders written before the one checkpoint layout (:func:`read_legacy_progress`).
LEGACY_PROGRESS = "progress.json"


def read_legacy_progress(out: str | Path) -> dict | None:
    """``progress.json`` of a pretraining run folder in the layout before ``checkpoints/`` (None when absent):
    the newest checkpoint's step, file names (``model_file``, ``optim_file``), optimizer groups and RNG state,
    and under ``previous`` the same for the one before it; :class:`BrokenCheckpoint` when it does not read."""
    p = Path(out) / LEGACY_PROGRESS
    return read_json(p) if p.exists() else None


def read_progress(out: str | Path) -> dict | None:
    """Progress of a pretraining run (None before the first checkpoint): ``state.json`` of its newest readable
    checkpoint (step, epoch, total_steps, finished, loss, optimizer groups, RNG state), else the legacy
    ``progress.json``."""
    state = newest_state(Path(out) / CHECKPOINTS)
    return state if state is not None else read_legacy_progress(out)
