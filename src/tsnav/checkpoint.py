"""Self-describing, pickle-free checkpoints for every trainer (pretraining, detector, agent): safetensors for
tensors, JSON for everything else, each file written atomically (:mod:`tsnav.atomic`).

A checkpoint that cannot be read (a truncated or corrupt file, e.g. after a full disk or a copy cut short)
raises :class:`BrokenCheckpoint` naming the file; :func:`resume_newest` then reports it in one line and resumes
from the previous checkpoint, which every trainer keeps.

The one on-disk layout of the three trainers (agent: ``RUN/checkpoints``; pretraining: ``OUT/checkpoints``;
detector: ``DIR/checkpoints``)::

    checkpoints/ckpt_<step, 9 digits>/   model.safetensors      weights; trainer metadata (format, config)
                                         optimizer.safetensors  optimizer state tensors (agent checkpoints
                                                                written before: optim.safetensors, still read)
                                         state.json             progress and the trainer's JSON fields
                                         (agent: rng_rank<r>.json, RNG states per rank)

A checkpoint is written complete in a temporary folder and renamed, so a folder ``ckpt_<step>`` (no dot) with
a ``state.json`` is whole; the newest two are kept (plus the agent's milestones). A newest checkpoint broken
later is named in one line, renamed ``ckpt_<step>.broken`` and the one before it is used. The layout's names
and JSON files are in :mod:`tsnav.checkpoint_layout` (no torch), re-exported here.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path
from typing import Callable, Sequence, TypeVar

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save

from .atomic import atomic_folder, atomic_write_bytes, atomic_write_json as _atomic_write_json

# The layout and its JSON files live in the torch-free checkpoint_layout; re-exported here.
from .checkpoint_layout import (  # noqa: F401
    CHECKPOINTS,
    MODEL_FILE,
    OLD_OPTIMIZER_FILE,
    OPTIMIZER_FILE,
    STATE_FILE,
    BrokenCheckpoint,
    _one_line,
    checkpoint_name,
    checkpoint_step,
    checkpoint_tmp,
    checkpoint_tmp_path,
    commit_checkpoint,
    list_checkpoints,
    newest_state,
    optimizer_file,
    prune_checkpoints,
    read_json,
    set_aside,
)

T = TypeVar("T")
R = TypeVar("R")


def atomic_write_json(path: str | Path, obj) -> None:
    """JSON of a checkpoint or run folder (indented, sorted keys), written atomically."""
    _atomic_write_json(path, obj, indent=1, sort_keys=True)


def save_tensors(path: str | Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    """Atomically write ``tensors`` as safetensors (contiguous CPU copies) with string ``metadata``."""
    t = {k: v.detach().to("cpu").contiguous() for k, v in tensors.items()}
    atomic_write_bytes(path, save(t, metadata=metadata))


def load_tensors(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of a safetensors file; :class:`BrokenCheckpoint` when it cannot be read."""
    out = {}
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            for k in f.keys():
                out[k] = f.get_tensor(k)
    except (SafetensorError, OSError) as e:
        raise BrokenCheckpoint(f"{path}: broken checkpoint file ({_one_line(e)})") from None
    return out, meta


def resume_newest(
    candidates: Sequence[T],
    load: Callable[[T], R],
    on_broken: Callable[[T], None] | None = None,
    label: Callable[[T], str] = str,
) -> tuple[T, R] | None:
    """Load the newest checkpoint that reads: ``candidates`` newest first, ``load(candidate)`` raising
    :class:`BrokenCheckpoint` for a broken one. Each broken one is reported on stderr in one line (which file,
    what is wrong, which checkpoint is used instead) and passed to ``on_broken`` (e.g. to set it aside).
    Returns ``(candidate, load result)``, None when there are no candidates; when every candidate is broken
    the last error is raised."""
    last: BrokenCheckpoint | None = None
    for i, c in enumerate(candidates):
        try:
            return c, load(c)
        except BrokenCheckpoint as e:
            last = e
            nxt = f"resuming from {label(candidates[i + 1])}" if i + 1 < len(candidates) else "no older checkpoint"
            print(f"tsnav: {e}; {nxt}", file=sys.stderr, flush=True)
            if on_broken is not None:
                on_broken(c)
    if last is not None:
        raise last
    return None


def optimizer_to_tensors(opt: torch.optim.Optimizer, names: list[str]) -> tuple[dict[str, torch.Tensor], dict]:
    """Flatten an optimizer's state: tensors keyed ``<param name>::<state key>`` plus JSON-able groups.

    ``names`` lists the parameter names in the order the optimizer's groups hold them.
    """
    sd = opt.state_dict()
    tensors, extra = {}, {}
    for idx, st in sd["state"].items():
        for k, v in st.items():
            if isinstance(v, torch.Tensor):
                tensors[f"{names[idx]}::{k}"] = v
            else:
                extra[f"{names[idx]}::{k}"] = v
    groups = []
    for g in sd["param_groups"]:
        groups.append(
            {k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items() if k != "params"}
            | {"params": [names[i] for i in g["params"]]}
        )
    return tensors, {"param_groups": groups, "extra_state": extra}


def optimizer_from_tensors(
    opt: torch.optim.Optimizer, names: list[str], tensors: dict[str, torch.Tensor], meta: dict
) -> None:
    """Inverse of :func:`optimizer_to_tensors`, loading into ``opt`` (built over the same parameters)."""
    index = {n: i for i, n in enumerate(names)}
    state: dict[int, dict] = {}
    for key, v in tensors.items():
        name, k = key.split("::", 1)
        state.setdefault(index[name], {})[k] = v
    for key, v in meta.get("extra_state", {}).items():
        name, k = key.split("::", 1)
        state.setdefault(index[name], {})[k] = v
    current = opt.state_dict()["param_groups"]
    groups = []
    for g, cur in zip(meta["param_groups"], current):
        g = dict(g)
        params = [index[n] for n in g.pop("params")]
        if params != cur["params"]:
            raise ValueError("optimizer checkpoint does not match the model's parameters")
        for k, v in g.items():
            if isinstance(cur.get(k), tuple):
                g[k] = tuple(v)
        groups.append(g | {"params": params})
    opt.load_state_dict({"state": state, "param_groups": groups})


def weights_digest(state_dict: dict[str, torch.Tensor], skip: tuple[str, ...] = (), extra: bytes = b"") -> str:
    """SHA-256 (hex) of a model's weights: names and bytes in sorted name order, without the entries whose
    names start with a prefix in ``skip``, then ``extra``. The one weight hash of tsnav (encoder and detector
    fingerprints, the agreement check of distributed ranks)."""
    h = hashlib.sha256()
    for k, v in sorted(state_dict.items()):
        if k.startswith(skip):
            continue
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    h.update(extra)
    return h.hexdigest()


def write_checkpoint_files(
    tmp: str | Path,
    model: dict[str, torch.Tensor],
    model_meta: dict[str, str] | None,
    state: dict,
    optimizer: dict[str, torch.Tensor] | None = None,
) -> None:
    """Write the files of one checkpoint into the (temporary) folder ``tmp``: ``model.safetensors`` (with
    ``model_meta``), ``optimizer.safetensors`` when ``optimizer`` tensors are given, ``state.json`` (the
    trainer's progress and JSON fields) last."""
    tmp = Path(tmp)
    save_tensors(tmp / MODEL_FILE, model, model_meta)
    if optimizer is not None:
        save_tensors(tmp / OPTIMIZER_FILE, optimizer)
    atomic_write_json(tmp / STATE_FILE, state)


def save_checkpoint(
    folder: str | Path,
    step: int,
    model: dict[str, torch.Tensor],
    model_meta: dict[str, str] | None,
    state: dict,
    optimizer: dict[str, torch.Tensor] | None = None,
    keep: int = 2,
    milestone_every: int | None = None,
) -> Path:
    """Write the checkpoint of ``step`` into ``folder/ckpt_<step>/`` (:func:`write_checkpoint_files` in a
    temporary folder, then :func:`commit_checkpoint`); returns its path."""
    final = Path(folder) / checkpoint_name(step)
    with atomic_folder(final) as tmp:
        write_checkpoint_files(tmp, model, model_meta, state, optimizer)
    prune_checkpoints(folder, keep, milestone_every)
    return final
