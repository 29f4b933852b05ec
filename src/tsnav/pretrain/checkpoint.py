"""Self-describing, pickle-free checkpoints: safetensors for tensors, JSON for everything else.

A checkpoint of step ``s`` in a run folder is ``ckpt-<s>-model.safetensors``, ``ckpt-<s>-optim.safetensors``
and ``progress.json`` (written last, atomically, naming those files): a crash at any point leaves either the
previous complete checkpoint or the new one.
"""

from __future__ import annotations

from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save

from ..atomic import atomic_write_bytes, atomic_write_json as _atomic_write_json


def atomic_write_json(path: str | Path, obj) -> None:
    _atomic_write_json(path, obj, indent=1, sort_keys=True)


def save_tensors(path: str | Path, tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> None:
    """Atomically write ``tensors`` as safetensors (contiguous CPU copies) with string ``metadata``."""
    t = {k: v.detach().to("cpu").contiguous() for k, v in tensors.items()}
    atomic_write_bytes(path, save(t, metadata=metadata))


def load_tensors(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and metadata of a safetensors file."""
    out = {}
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        for k in f.keys():
            out[k] = f.get_tensor(k)
    return out, meta


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
        groups.append({k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items() if k != "params"}
                      | {"params": [names[i] for i in g["params"]]})
    return tensors, {"param_groups": groups, "extra_state": extra}


def optimizer_from_tensors(opt: torch.optim.Optimizer, names: list[str], tensors: dict[str, torch.Tensor],
                           meta: dict) -> None:
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
