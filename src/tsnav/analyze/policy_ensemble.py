"""Evaluate an ensemble of trained agents: at every step each member runs on the same observation with its own LSTM
state and target memory, the action is the argmax of the members' summed action probabilities (or summed
log-probabilities, ``--average logprob``), and every member is told that action as its previous action (an issue 23
analysis; nothing here is shipped). The stage switch follows the first member's detection table; every member
reads its own training table and features.

Writes what ``tsnav eval`` writes (``records.jsonl``, ``trajectories.jsonl``, ``outcomes.json``, ``metrics.json``
with ``policy: ensemble`` and the members' runs), so ``tsnav analyze agent-diagnostics`` reads the folder. A one-member
ensemble acts exactly as ``tsnav eval --run`` does (tested).

    tsnav analyze policy-ensemble --data WORLD --episodes TEST.json --run RUN_A --run RUN_B --out OUT
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import CommandError
from ..eval.runner import (
    EvalConfig,
    config_dict,
    load_bank_for_episodes,
    record_trajectories,
    resolve_protocol,
    write_evaluation,
)
from ..metrics import summarize
from ..rl.checkpoint import load_policy
from ..rl.policy import AgentPolicy
from ..sim.episodes import read_episodes

AVERAGES = ("prob", "logprob")


class EnsemblePolicy:
    """Greedy ensemble of :class:`~tsnav.rl.policy.AgentPolicy` members (module docstring)."""

    def __init__(self, members: list[AgentPolicy], average: str = "prob"):
        if not members:
            raise ValueError("an ensemble needs at least one member")
        if average not in AVERAGES:
            raise ValueError(f"average must be one of {AVERAGES}, got {average!r}")
        self.members = members
        self.average = average

    def reset(self, mask: np.ndarray) -> None:
        for m in self.members:
            m.reset(mask)

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        norm = torch.softmax if self.average == "prob" else torch.log_softmax
        steps = [m.logits(obs) for m in self.members]
        action = sum(norm(logits.float(), dim=1) for logits, _ in steps).argmax(dim=1)
        for m, (_, state) in zip(self.members, steps):
            m.commit(state, action)
        return action.cpu().numpy().astype(np.int64)


def evaluate_ensemble(
    out: Path,
    data: Path,
    episodes_file: Path,
    runs: list[Path],
    checkpoint: str = "best",
    average: str = "prob",
    protocol: str | None = None,
    max_steps: int = 100,
) -> dict:
    """Evaluate the ensemble of ``runs`` on an episode list into ``out`` (the files of ``tsnav eval``)."""
    episodes, emeta = read_episodes(episodes_file)
    if not episodes:
        raise CommandError(f"{episodes_file}: the episode list is empty")
    protocol, trained = resolve_protocol(emeta, episodes_file, runs[0], protocol)
    config = EvalConfig(max_steps=max_steps)
    bank = load_bank_for_episodes(
        data,
        episodes,
        success_distance=float(emeta.get("success_distance", 1.0)),
        c_target=config.c_target,
        protocol=protocol,
    )
    policy = EnsemblePolicy([load_policy(r, bank, checkpoint=checkpoint) for r in runs], average)
    t0 = time.perf_counter()
    records, trajectories = record_trajectories(bank, episodes, policy, config)
    summary = summarize(records, config.min_optimal_length, protocol=protocol)
    meta = {
        "policy": "ensemble",
        "runs": [str(Path(r).resolve()) for r in runs],
        "average": average,
        "checkpoint": checkpoint,
        "episodes_file": str(Path(episodes_file).resolve()),
        "data": str(Path(data).resolve()),
        "protocol": protocol,
        "trained_protocol": trained,
        "success_distance": float(emeta.get("success_distance", 1.0)),
        "detections": None,
        "config": config_dict(config),
        "label": f"ensemble of {len(runs)}",
    }
    write_evaluation(out, meta, summary, records, trajectories, bank, time.perf_counter() - t0)
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False,
        prog="tsnav analyze policy-ensemble",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawTextHelpFormatter,
    )
    p.add_argument("--data", type=Path, required=True, help="dataset root (scene folders)")
    p.add_argument("--episodes", type=Path, required=True, help="episode list JSON")
    p.add_argument(
        "--run",
        type=Path,
        action="append",
        required=True,
        help="a member's `tsnav train` run folder (repeat for each member)",
    )
    p.add_argument("--checkpoint", default="best", help="which checkpoint of every run (auto, best, latest)")
    p.add_argument("--average", choices=AVERAGES, default="prob", help="sum probabilities or log-probabilities")
    p.add_argument("--protocol", default=None, help="success protocol (default: the episode list's)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    a = p.parse_args(argv)
    for r in a.run:
        if not (r / "config.json").is_file():
            print(f"error: {r}: not a `tsnav train` run folder (no config.json)", file=sys.stderr)
            return 2
    try:
        s = evaluate_ensemble(a.out, a.data, a.episodes, a.run, a.checkpoint, a.average, a.protocol)
    except (CommandError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    m = s["ALL"]
    print(
        f"ensemble of {len(a.run)} ({a.average}), {m['episodes']} episodes: SR {100 * m['SR']:.2f}  "
        f"SPL {100 * m['SPL']:.2f}  -> {a.out}"
    )
    return 0
