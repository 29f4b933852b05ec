"""Could a stop head stop a trained agent sooner than its own Done? A small network is trained on the agent's own
inputs to tell a success state from the rest, and Done is then called where it says so.

    tsnav analyze stop-head --run RUN --data WORLD --train TRAIN.json [TRAIN.json ...] --val VAL.json
        --test TEST.json [TEST.json ...] [--inputs state,detection] [--checkpoint best] [--detections NAME]
        [--depth-readout FILE] [--json OUT.json] [--out DIR]

1. The agent walks every episode of the lists greedily with Done taken away (the most probable of the five
   movement actions, 100 steps): up to the step where it would have called Done this is its own walk, so a stop
   rule applied afterwards replays what that rule would have done in a real evaluation.
2. On the training lists' walks, the head (an MLP, 256 hidden units, on standardised inputs) learns whether each
   step's state is a success state of the episode's target under the validation list's protocol (the label is
   privileged: it is read to train and to score the head, never by the agent). ``--inputs`` chooses what it sees, all
   of it what the agent sees: ``state`` (the LSTM hidden state after the step), ``detection`` (the target's box,
   score and the camera's horizon in this frame), ``image`` (the encoder's feature map of this frame), ``est-depth``
   (the depth inside the target's box, median, minimum and 10th percentile, as a readout of the encoder's feature
   map estimates it: ``--depth-readout``, from `tsnav analyze depth-readout`). One input is not the agent's, a
   diagnostic of what a signal would be worth: ``true-depth``, the world's ground-truth depth inside the target's
   box (the same statistics; ``depth.hdf5`` averaged to 32x32), which no agent may read at test time; figures with
   it bound what an estimate of that depth could give. Trained on the steps up to three after the walk's first
   success state (at most step 40): where the stop decision is made.
   (The walks' inputs are held in memory, float16: ``image`` at 4x4 tokens of 192 channels takes about 2.5 GB per
   4000 training episodes.)
3. On the validation list each threshold of the head's probability is scored (Done at the first step above it),
   and the one with the best SPL is kept; the test lists are scored at it, with two references on the same walks:
   the agent's own Done, and Done at the first success state of the walk (no stop rule can do better on it).

Rules: ``head`` (Done only where the head says so) and ``head or agent`` (Done where either does). Every figure is
counted as ``tsnav eval`` counts it (SR and SPL under the list's protocol). Checked while it runs, the slow
reference beside the replay: the agent's own Done replayed must give every episode of every list the success, path
and steps of a real evaluation of the agent, and both head rules at the chosen threshold those of a real evaluation of
the agent with the head deciding Done on every test list; a difference stops the command. ``--out DIR`` writes the latter evaluation (one test list) into
``DIR/PROTOCOL`` as an evaluation folder, for `tsnav analyze lever-table`.
"""

from __future__ import annotations

import argparse
import json
import sys
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_json
from ..constants import C_TARGET, DONE
from ..protocol import protocol_of
from ..pretrain.depth_readout import GRID as DEPTH_GRID  # side of the depth maps both depth inputs read
from .stop_ceiling import sr_spl, stopped_records

INPUTS = ("state", "detection", "image", "est-depth", "true-depth")
#: Inputs that are not what the agent sees (diagnostics: what such a signal would be worth).
DIAGNOSTIC_INPUTS = ("true-depth",)
#: Thresholds of the head's probability scored on the validation list.
THRESHOLDS = (0.3, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 0.98)
#: Training steps kept per episode: up to this many after the walk's first success state, and at most ``TRAIN_CAP``.
AFTER_FIRST = 3
TRAIN_CAP = 40


class BankDepth:
    """The ground-truth depth frames of a bank's states (``depth.hdf5`` of each scene), averaged down to
    :data:`DEPTH_GRID` squared, for the ``true-depth`` diagnostic input."""

    def __init__(self, bank):
        from ..pretrain.depth_readout import scene_depth_maps

        self.depth = np.zeros((bank.num_states, DEPTH_GRID, DEPTH_GRID), dtype=np.float16)
        for i, scene in enumerate(bank.scenes):
            path = scene.depth_path()
            if path is None:
                raise ValueError(f"{scene.path}: no depth.hdf5 (true-depth needs the world's depth frames)")
            # averaged as they are, unclipped (the figures of the true-depth rows were made so)
            d = scene_depth_maps(path, scene.keys, max_depth=None, flip=scene.mirror)
            self.depth[int(bank.offsets[i]) : int(bank.offsets[i + 1])] = d

    def in_box(self, states, boxes, scores) -> np.ndarray:
        """:func:`box_depth` of the states' depth maps."""
        return box_depth(self.depth[np.asarray(states)], boxes, scores)

    def in_box_reference(self, states, boxes, scores) -> np.ndarray:
        """:func:`box_depth_reference` of the states' depth maps."""
        return box_depth_reference(self.depth[np.asarray(states)], boxes, scores)


def _cells(boxes) -> np.ndarray:
    """``(B, 4)`` cell bounds x0, y0, x1, y1 of boxes given as fractions of the frame, at least one cell each (the
    agent's :func:`~tsnav.agent.observe.box_cells`)."""
    import torch

    from ..agent.observe import box_cells

    return box_cells(torch.as_tensor(np.asarray(boxes), dtype=torch.float32), DEPTH_GRID).numpy()


def box_depth(depth, boxes, scores) -> np.ndarray:
    """``(B, 3)``: median, minimum and 10th percentile of each row's depth map ``depth (B, DEPTH_GRID, DEPTH_GRID)``
    (metres) inside its box (fractions of the frame, at least one cell); 9, 9, 9 where nothing is detected (score
    0). Array code over the batch; the loop of :func:`box_depth_reference` beside it. (An agent's own depth input,
    :func:`~tsnav.agent.observe.box_depth_stats`, takes the lower element for its quantiles and clips to 5 m.)"""
    out = np.full((len(depth), 3), 9.0, dtype=np.float32)
    rows = np.flatnonzero(np.asarray(scores) > 0)
    if not len(rows):
        return out
    c = _cells(np.asarray(boxes)[rows])
    grid = np.arange(DEPTH_GRID)
    inside_x = (grid[None, :] >= c[:, 0:1]) & (grid[None, :] < c[:, 2:3])
    inside_y = (grid[None, :] >= c[:, 1:2]) & (grid[None, :] < c[:, 3:4])
    d = np.asarray(depth)[rows].astype(np.float32)
    d = np.where(inside_y[:, :, None] & inside_x[:, None, :], d, np.nan).reshape(len(rows), -1)
    out[rows] = np.stack([np.nanmedian(d, axis=1), np.nanmin(d, axis=1), np.nanpercentile(d, 10, axis=1)], axis=1)
    return out


def box_depth_reference(depth, boxes, scores) -> np.ndarray:
    """Slow reference of :func:`box_depth`: one box at a time."""
    out = np.full((len(depth), 3), 9.0, dtype=np.float32)
    for r in range(len(depth)):
        if scores[r] > 0:
            x0, y0, x1, y1 = _cells(np.asarray(boxes)[r : r + 1])[0]
            patch = np.asarray(depth[r])[y0:y1, x0:x1].astype(np.float32).ravel()
            out[r] = (np.median(patch), patch.min(), np.percentile(patch, 10))
    return out


_DEPTHS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


@dataclass
class Depths:
    """Where the depth inputs come from: ``true`` the bank's ground truth (``true-depth``), ``readout`` a
    :class:`~tsnav.pretrain.depth_readout.DepthReadout` of the agent's feature map (``est-depth``)."""

    true: BankDepth | None = None
    readout: object | None = None


def depth_for(bank, inputs, readout=None) -> Depths:
    """The depth sources ``inputs`` asks for: the bank's :class:`BankDepth` for ``true-depth`` (read once per bank),
    ``readout`` for ``est-depth`` (``ValueError`` when it is asked for and not given)."""
    true = None
    if "true-depth" in inputs:
        if bank not in _DEPTHS:
            _DEPTHS[bank] = BankDepth(bank)
        true = _DEPTHS[bank]
    if "est-depth" in inputs and readout is None:
        raise ValueError("est-depth needs a depth readout (--depth-readout, from `tsnav analyze depth-readout`)")
    return Depths(true, readout if "est-depth" in inputs else None)


def step_inputs(policy, obs, state, inputs, depth: Depths | None = None) -> np.ndarray:
    """``(B, D)`` float32: the parts of what the agent sees at this step that ``inputs`` names: ``est-depth`` the
    readout's depth of the agent's feature map inside the target's box; the diagnostic ``true-depth`` the
    ground-truth depth there (both from ``depth``)."""
    import torch

    parts = []
    if "state" in inputs:
        parts.append(state.h)
    if any(i in inputs for i in ("detection", "image", "est-depth", "true-depth")):
        o = policy.observer(obs["state"], obs["target"])
        box, score = o.det_box.cpu().numpy(), o.det_score.cpu().numpy()
        if "detection" in inputs:
            parts.append(torch.cat([o.det_box, o.det_score[:, None], o.pose[:, 3:4] / 30.0], dim=1))
        if "image" in inputs:
            parts.append(o.image.flatten(1))
        if "est-depth" in inputs:
            with torch.no_grad():
                maps = depth.readout(o.image.float().cpu()).numpy()
            parts.append(torch.from_numpy(box_depth(maps, box, score)))
        if "true-depth" in inputs:
            parts.append(torch.from_numpy(depth.true.in_box(np.asarray(obs["state"]), box, score)))
    return torch.cat(parts, dim=1).float().cpu().numpy()


class WalkWithoutDone:
    """Wraps an :class:`~tsnav.rl.policy.AgentPolicy`: acts with the most probable movement action (Done taken away)
    and records per step, for the rows ``obs["active"]``, whether the agent wanted Done, whether the state is a
    success state (``success[state, target]``) and either the head's probability (``head`` given) or the inputs."""

    def __init__(self, policy, success: np.ndarray, inputs, head=None, depth=None):
        self.policy, self.success, self.inputs, self.head, self.depth = policy, success, tuple(inputs), head, depth
        self.active, self.wish, self.label, self.values = [], [], [], []
        # inputs (no head: a training walk) are kept for the steps the head is trained on only
        self.keep_values = None if head is not None else TRAIN_CAP + 1

    def reset(self, mask) -> None:
        self.policy.reset(mask)

    def act(self, obs) -> np.ndarray:
        logits, state = self.policy.logits(obs)
        x = step_inputs(self.policy, obs, state, self.inputs, self.depth)
        self.active.append(np.asarray(obs["active"], dtype=bool).copy())
        self.wish.append((logits.argmax(dim=1) == DONE).cpu().numpy())
        self.label.append(self.success[obs["state"], obs["target"]].copy())
        if self.head is not None:
            self.values.append(self.head.probability(x))
        elif len(self.values) < self.keep_values:
            self.values.append(x.astype(np.float16))
        action = logits[:, :DONE].argmax(dim=1)
        self.policy.commit(state, action)
        return action.cpu().numpy().astype(np.int64)

    def arrays(self) -> dict:
        """``active``, ``wish``, ``label`` ``(B, T)`` and ``values`` ``(B, T)`` (probabilities) or, for a training
        walk, ``(B, min(T, TRAIN_CAP + 1), D)`` (the inputs)."""
        return {k: np.stack(getattr(self, k), axis=1) for k in ("active", "wish", "label", "values")}


class HeadDecidesDone:
    """The agent with the head deciding Done (``rule`` ``head``: only there; ``head or agent``: also where the agent
    wants it), the walk otherwise the agent's: a real policy for the evaluation runner."""

    def __init__(self, policy, head, inputs, threshold: float, rule: str = "head", depth=None):
        self.policy, self.head, self.inputs, self.threshold, self.rule = policy, head, tuple(inputs), threshold, rule
        self.depth = depth

    def reset(self, mask) -> None:
        self.policy.reset(mask)

    def act(self, obs) -> np.ndarray:
        import torch

        logits, state = self.policy.logits(obs)
        stop = self.head.probability(step_inputs(self.policy, obs, state, self.inputs, self.depth)) > self.threshold
        if self.rule == "head or agent":
            stop |= (logits.argmax(dim=1) == DONE).cpu().numpy()
        move = logits[:, :DONE].argmax(dim=1).cpu().numpy()
        action = np.where(stop, DONE, move).astype(np.int64)
        self.policy.commit(state, torch.from_numpy(action))
        return action


@dataclass
class Head:
    """The stop head: standardisation, then ``Linear(D, hidden) - ReLU - Linear(hidden, 1)``."""

    net: object
    mean: np.ndarray
    std: np.ndarray

    def probability(self, x: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            z = torch.from_numpy(((x - self.mean) / self.std).astype(np.float32))
            return torch.sigmoid(self.net(z)[:, 0]).numpy()


def train_head(x: np.ndarray, y: np.ndarray, hidden: int = 256, epochs: int = 6, seed: int = 0) -> Head:
    """Fit the head by binary cross-entropy (Adam, lr 1e-3, batches of 1024, dropout 0.2), seeded."""
    import torch
    import torch.nn as nn

    if not len(x) or y.all() or not y.any():
        raise ValueError("the training walks hold no success state or nothing else: more training episodes needed")
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    mean = x.mean(axis=0).astype(np.float32)
    std = (x.std(axis=0) + 1e-3).astype(np.float32)
    xt = torch.from_numpy(((x - mean) / std).astype(np.float32))
    yt = torch.from_numpy(y.astype(np.float32))
    net = nn.Sequential(nn.Linear(x.shape[1], hidden), nn.ReLU(), nn.Dropout(0.2), nn.Linear(hidden, 1))
    opt = torch.optim.Adam(net.parameters(), lr=1e-3, weight_decay=1e-4)
    net.train()
    for _ in range(epochs):
        perm = torch.randperm(len(xt), generator=gen)
        for i in range(0, len(xt), 1024):
            idx = perm[i : i + 1024]
            loss = nn.functional.binary_cross_entropy_with_logits(net(xt[idx])[:, 0], yt[idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
    net.eval()
    return Head(net, mean, std)


def first_fire(fire: np.ndarray, active: np.ndarray) -> np.ndarray:
    """``(B,)`` the first step of each row where ``fire & active``; -1 where none."""
    f = fire & active
    return np.where(f.any(axis=1), f.argmax(axis=1), -1)


def first_fire_reference(fire, active) -> list[int]:
    """Slow reference of :func:`first_fire`: a loop per row."""
    out = []
    for row_f, row_a in zip(np.asarray(fire), np.asarray(active)):
        out.append(next((t for t, (f, a) in enumerate(zip(row_f, row_a)) if f and a), -1))
    return out


def replay(records, label: np.ndarray, stop: np.ndarray):
    """The walk's records (Done taken away: every one a failure at the step limit) with Done at step ``stop[i]``
    (-1: never, the record unchanged): success is the label there, the path the ``stop[i]`` movement actions before
    (:func:`~tsnav.analyze.stop_ceiling.stopped_records`)."""
    if len(records) != len(stop):
        raise ValueError(f"{len(records)} records for {len(stop)} stop steps")
    stop = np.asarray(stop, dtype=np.int64)
    success = label[np.arange(len(stop)), np.maximum(stop, 0)]
    return stopped_records(records, stop, success)


def _bank(data, episodes, meta, protocol):
    """The list's bank, as `tsnav eval` builds it (the list's success distance, C_target 0.7)."""
    from ..eval.runner import load_bank_for_episodes

    distance = float(meta.get("success_distance", 1.0))
    return load_bank_for_episodes(data, episodes, success_distance=distance, protocol=protocol, c_target=C_TARGET)


def walk(run, data, episodes_file, checkpoint, inputs, protocol, head=None, detections=None, readout=None):
    """``(arrays, records, bank, episodes)`` of the agent's walks without Done on one list (:class:`WalkWithoutDone`)."""
    from ..eval.runner import EvalConfig, evaluate
    from ..rl.checkpoint import load_policy
    from ..sim.episodes import read_episodes

    episodes, meta = read_episodes(episodes_file)
    bank = _bank(data, episodes, meta, protocol)
    rec = WalkWithoutDone(
        load_policy(run, bank, checkpoint=checkpoint, detections=detections),
        bank.success,
        inputs,
        head,
        depth_for(bank, inputs, readout),
    )
    records = evaluate(bank, episodes, rec, EvalConfig(batch_size=len(episodes)))  # one chunk: (B, T) arrays
    return rec.arrays(), records, bank, episodes


def real_eval(
    run,
    bank,
    episodes,
    checkpoint,
    protocol,
    head=None,
    inputs=(),
    threshold=None,
    rule="head",
    out=None,
    meta=None,
    detections=None,
    readout=None,
) -> list:
    """The records of a real evaluation: the agent, or the agent with the head deciding Done; with ``out``, its
    evaluation folder (records, trajectories, outcomes, metrics.json with ``meta``) is written there."""
    import time

    from ..eval.runner import EvalConfig, record_trajectories, write_evaluation
    from ..metrics import summarize
    from ..rl.checkpoint import load_policy

    policy = load_policy(run, bank, checkpoint=checkpoint, detections=detections)
    if head is not None:
        policy = HeadDecidesDone(policy, head, inputs, threshold, rule, depth_for(bank, inputs, readout))
    t0 = time.perf_counter()
    records, trajectories = record_trajectories(bank, episodes, policy, EvalConfig(batch_size=len(episodes)))
    if out is not None:
        summary = summarize(records, protocol=protocol)
        write_evaluation(Path(out), meta, summary, records, trajectories, bank, time.perf_counter() - t0)
    return records


def check_same(replayed, real, what: str) -> None:
    """Raise when a replayed rule and its real evaluation differ in any episode's success, path or steps."""
    key = [(r.success, r.path_length, r.steps) for r in replayed]
    ref = [(r.success, r.path_length, r.steps) for r in real]
    if len(key) != len(ref):
        raise RuntimeError(f"{what}: {len(key)} replayed episodes against {len(ref)} evaluated")
    for i, (a, b) in enumerate(zip(key, ref)):
        if a != b:
            raise RuntimeError(f"{what}: the replay differs from its real evaluation (episode {i}: {a} against {b})")


def rule_stops(arrays, rule: str, tau: float | None = None) -> np.ndarray:
    """The step where ``rule`` (``agent``, ``first success``, ``head``, ``head or agent``) calls Done on each walk."""
    act, lab, p, wish = arrays["active"], arrays["label"], arrays["values"], arrays["wish"]
    fire = {"agent": lambda: wish, "first success": lambda: lab, "head": lambda: p > tau}
    fire["head or agent"] = lambda: (p > tau) | wish
    return first_fire(fire[rule](), act)


def score_list(arrays, records, protocol, thresholds) -> dict:
    """The rows of one list's walks: the agent, the first success state, and per threshold both head rules."""
    lab = arrays["label"]

    def scored(rule, tau=None):
        return sr_spl(replay(records, lab, rule_stops(arrays, rule, tau)), protocol)

    rows = {"agent": scored("agent"), "Done at the first success state of the walk": scored("first success")}
    sweep = [
        {"threshold": tau, "head": scored("head", tau), "head or agent": scored("head or agent", tau)}
        for tau in thresholds
    ]
    return {"episodes": len(records), "rows": rows, "sweep": sweep}


def analyse(
    run,
    data,
    train,
    val,
    tests,
    inputs=("state", "detection"),
    checkpoint="best",
    epochs=6,
    seed=0,
    out=None,
    detections=None,
    readout=None,
    log=print,
):
    """The whole analysis (module docstring); returns the results dict. ``out``: the head's evaluation of the (one)
    test list is written as an evaluation folder into ``out/PROTOCOL`` (for `tsnav analyze lever-table`)."""
    from ..sim.episodes import read_episodes

    protocol = protocol_of(read_episodes(val)[1])
    for t in [*train, *tests]:
        if protocol_of(read_episodes(t)[1]) != protocol:
            raise ValueError(f"{t}: drawn under another protocol than {val} ({protocol}): use lists of one protocol")
    xs, ys = [], []
    for f in train:
        arrays, _, _, _ = walk(run, data, f, checkpoint, inputs, protocol, detections=detections, readout=readout)
        width = arrays["values"].shape[1]  # the steps whose inputs were kept
        act, lab = arrays["active"][:, :width], arrays["label"][:, :width]
        first = np.where(lab.any(axis=1), lab.argmax(axis=1), lab.shape[1] - 1)
        keep = act & (np.arange(lab.shape[1])[None, :] <= np.minimum(first + AFTER_FIRST, TRAIN_CAP)[:, None])
        xs.append(arrays["values"][keep].astype(np.float32))
        ys.append(lab[keep])
        log(f"{f}: {int(keep.sum())} training steps")
    x, y = np.concatenate(xs), np.concatenate(ys)
    head = train_head(x, y, epochs=epochs, seed=seed)
    log(f"head trained on {len(x)} steps ({100 * y.mean():.1f} % success states), inputs {', '.join(inputs)}")
    result = {
        "format": "tsnav-stop-head",
        "run": str(run),
        "checkpoint": str(checkpoint),
        "detections": detections,
        "inputs": list(inputs),
        "diagnostic_inputs": [i for i in inputs if i in DIAGNOSTIC_INPUTS],
        "protocol": protocol,
        "epochs": epochs,
        "seed": seed,
        "train": {"lists": [str(f) for f in train], "steps": int(len(x)), "success_share": float(y.mean())},
    }

    def scored(f):
        arrays, records, bank, episodes = walk(run, data, f, checkpoint, inputs, protocol, head, detections, readout)
        res = score_list(arrays, records, protocol, THRESHOLDS)
        real = real_eval(run, bank, episodes, checkpoint, protocol, detections=detections)
        check_same(replay(records, arrays["label"], rule_stops(arrays, "agent")), real, f"{f}, the agent's own Done")
        return res, bank, episodes, arrays, records

    v, _, _, _, _ = scored(val)
    best = max(v["sweep"], key=lambda s: (s["head"]["SPL"], s["head"]["SR"]))
    tau = best["threshold"]
    result["val"] = {"list": str(val), **v, "chosen_threshold": tau}
    log(f"{val}: agent {_fmt(v['rows']['agent'])}; head at {tau} (best val SPL) {_fmt(best['head'])}")
    result["test"] = []
    for f in tests:
        t, bank, episodes, arrays, records = scored(f)
        at = next(s for s in t["sweep"] if s["threshold"] == tau)
        for rule in ("head", "head or agent"):
            folder = Path(out) / protocol if out is not None and rule == "head" else None
            meta = {
                "policy": "stop-head (tsnav analyze stop-head; not rebuilt by tsnav eval)",
                "run": None,
                "agent_run": str(Path(run).resolve()),
                "checkpoint": str(checkpoint),
                "stop_head": {"inputs": list(inputs), "threshold": tau, "rule": rule, "train": [str(x) for x in train]},
                "detections": detections,
                "episodes_file": str(Path(f).resolve()),
                "data": str(Path(data).resolve()),
                "protocol": protocol,
                "success_distance": float(bank.success_distance),
                "config": {"max_steps": 100, "c_target": C_TARGET},
                "label": f"agent {Path(run).name} with a stop head at {tau}",
            }
            real = real_eval(
                run, bank, episodes, checkpoint, protocol, head, inputs, tau, rule, folder, meta, detections, readout
            )
            check_same(replay(records, arrays["label"], rule_stops(arrays, rule, tau)), real, f"{f}, {rule} at {tau}")
        t["rows"][f"head at {tau}"] = at["head"]
        t["rows"][f"head or agent at {tau}"] = at["head or agent"]
        result["test"].append({"list": str(f), **t})
        log(f"{f}: " + "; ".join(f"{k} {_fmt(r)}" for k, r in t["rows"].items()))
    return result


def check_readout(meta: dict, run, data, path) -> None:
    """``ValueError`` when the readout was trained on the features of another encoder than the run reads."""
    from ..data.reader import list_scenes
    from ..pretrain.features import feature_fingerprint
    from ..rl.checkpoint import read_run_config

    name = read_run_config(run)["train"]["features"]
    scenes = [s for s in list_scenes(data) if (s / f"features_{name}.hdf5").exists()]
    if not scenes:
        raise ValueError(f"{data}: no scene has the run's features_{name}.hdf5")
    fp = feature_fingerprint(scenes[0], name)
    if meta.get("fingerprint") and fp and meta["fingerprint"] != fp:
        raise ValueError(f"{path}: a readout of the features of encoder {meta['fingerprint']}, the run reads {fp}")


def _fmt(r: dict) -> str:
    return f"SR {r['SR']:.2f} SPL {r['SPL']:.2f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze stop-head", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--run", type=Path, required=True, help="a training run or shipped agent folder")
    ap.add_argument("--data", type=Path, required=True, help="the world (scene folders with the run's features)")
    ap.add_argument("--train", type=Path, nargs="+", required=True, help="episode lists of the training rooms")
    ap.add_argument("--val", type=Path, required=True, help="the episode list that chooses the threshold")
    ap.add_argument("--test", type=Path, nargs="+", required=True, help="episode lists scored at that threshold")
    ap.add_argument("--inputs", default="state,detection", help=f"what the head sees, of {', '.join(INPUTS)}")
    ap.add_argument("--checkpoint", default="best", help="the run's checkpoint (as tsnav eval --checkpoint)")
    ap.add_argument(
        "--detections", default=None, help="the detection table the agent reads (default: its training one)"
    )
    ap.add_argument(
        "--depth-readout",
        type=Path,
        default=None,
        help="for --inputs est-depth: a readout of the agent's feature map (`tsnav analyze depth-readout`)",
    )
    ap.add_argument("--epochs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--out", type=Path, default=None, help="write the head's evaluation of the one --test list into OUT/PROTOCOL"
    )
    args = ap.parse_args(argv)
    if args.out is not None and len(args.test) != 1:
        print(
            "tsnav analyze stop-head: --out takes one --test list (its evaluation goes to OUT/PROTOCOL)",
            file=sys.stderr,
        )
        return 2
    inputs = tuple(s.strip() for s in args.inputs.split(",") if s.strip())
    bad = [s for s in inputs if s not in INPUTS]
    if bad or not inputs:
        print(f"tsnav analyze stop-head: --inputs {args.inputs!r}: choose from {', '.join(INPUTS)}", file=sys.stderr)
        return 2
    if args.epochs < 1:
        print(f"tsnav analyze stop-head: --epochs must be >= 1, got {args.epochs}", file=sys.stderr)
        return 2
    for f in [*args.train, args.val, *args.test]:
        if not f.is_file():
            print(f"tsnav analyze stop-head: {f}: no such episode list", file=sys.stderr)
            return 2
    if not (args.run / "config.json").is_file():
        print(
            f"tsnav analyze stop-head: {args.run}: not a training run or agent folder (no config.json)", file=sys.stderr
        )
        return 2
    if (args.depth_readout is not None) != ("est-depth" in inputs):
        print(
            "tsnav analyze stop-head: --depth-readout goes with --inputs ...,est-depth, and only with it",
            file=sys.stderr,
        )
        return 2
    try:
        readout = None
        if args.depth_readout is not None:
            from ..pretrain.depth_readout import load_readout

            readout, readout_meta = load_readout(args.depth_readout)
            check_readout(readout_meta, args.run, args.data, args.depth_readout)
        res = analyse(
            args.run,
            args.data,
            args.train,
            args.val,
            args.test,
            inputs,
            args.checkpoint,
            args.epochs,
            args.seed,
            out=args.out,
            detections=args.detections,
            readout=readout,
        )
        if "est-depth" in inputs:
            res["depth_readout"] = {
                "file": str(args.depth_readout),
                **{k: readout_meta.get(k) for k in ("features", "fingerprint", "epochs", "seed")},
                "scores": json.loads(readout_meta.get("scores", "{}")),
            }
    except (ValueError, RuntimeError) as e:
        print(f"tsnav analyze stop-head: {e}", file=sys.stderr)
        return 2
    if args.json:
        atomic_write_json(args.json, res, sort_keys=False)
        print(f"wrote {args.json}")
    return 0
