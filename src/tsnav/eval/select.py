"""``tsnav select``: choose a run's checkpoint on validation episodes (issue 15; the paper trains for a fixed
budget, but a CPU-scale run overfits its rooms before the budget ends, so the checkpoint kept is the one that
navigates the validation rooms best).

Every checkpoint the run kept (its milestones, ``tsnav train --milestone-every N``, and the newest two) is
evaluated on a fixed validation episode list with greedy actions (the lineage's test-time rule); the scores go
to ``RUN/selection.json`` (rewritten atomically after each checkpoint, so an interrupted selection resumes and
scores only what is new; a checkpoint whose weights file has the size and modification time recorded with its
score is not even reloaded and rehashed), and the best - highest SR, then SPL, then the earliest update - is copied to
``RUN/best/`` (a temporary folder renamed when complete). ``tsnav eval --run RUN`` then evaluates ``best``
unless told ``--checkpoint latest|PATH``.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from ..atomic import atomic_folder, atomic_write_json
from ..checkpoint import MODEL_FILE, BrokenCheckpoint, read_json, weights_digest
from ..constants import C_TARGET
from ..errors import CommandError
from ..metrics import summarize
from ..rl.checkpoint import BEST, list_checkpoints, load_model, load_policy
from ..sim.episodes import read_episodes
from .runner import EvalConfig, evaluate, load_bank_for_episodes, resolve_protocol
from ..settings import add_shared

SELECTION = "selection.json"
#: Metrics that rank checkpoints, in order (ALL episodes).
RANK_BY = ("SR", "SPL")


def file_signature(path: Path) -> list[int]:
    """``[size in bytes, modification time in ns]`` of ``path``: a checkpoint's weights file whose signature is
    the one recorded with its score has not changed since (checkpoints are written whole and renamed), so its
    digest is reused instead of loading and hashing the weights again."""
    st = Path(path).stat()
    return [int(st.st_size), int(st.st_mtime_ns)]


def _digest(run_dir: Path, ck: Path) -> str:
    """:func:`~tsnav.checkpoint.weights_digest` of the agent weights of checkpoint folder ``ck``."""
    return weights_digest(load_model(run_dir, ck)[0].state_dict())


def select_checkpoint(
    run_dir: str | Path,
    data: str | Path,
    episodes_file: str | Path,
    *,
    seed: int = 0,
    max_steps: int = 100,
    c_target: float = C_TARGET,
    progress=print,
    protocol: str | None = None,
) -> dict:
    """Score every kept checkpoint of ``run_dir`` on ``episodes_file`` (greedy, episode length ``max_steps``,
    stage-switch threshold ``c_target``), keep the best as ``RUN/best``; returns the selection (``scores``:
    checkpoint name -> update, digest, metrics; ``best``; ``protocol``). The success protocol is the episode
    list's; a run trained under another one is refused unless ``protocol`` names the list's
    (:func:`~tsnav.eval.runner.resolve_protocol`)."""
    run_dir = Path(run_dir)
    ckpts = list_checkpoints(run_dir)
    if not ckpts:
        raise FileNotFoundError(f"{run_dir}: no checkpoint to select from")
    episodes, emeta = read_episodes(episodes_file)
    if not episodes:
        raise ValueError(f"{episodes_file}: the episode list is empty")
    protocol, _ = resolve_protocol(emeta, episodes_file, run_dir, protocol)
    path = run_dir / SELECTION
    try:
        old = read_json(path) if path.exists() else {}
    except BrokenCheckpoint:  # an unreadable score cache is recomputed
        old = {}
    same_list = (
        old.get("episodes_file") == str(Path(episodes_file).resolve())
        and old.get("max_steps") == max_steps
        and old.get("c_target", C_TARGET) == c_target
        and old.get("protocol", "paper") == protocol
    )
    scores = dict(old.get("scores", {})) if same_list else {}
    bank = load_bank_for_episodes(
        data, episodes, success_distance=float(emeta.get("success_distance", 1.0)), protocol=protocol
    )
    config = EvalConfig(max_steps=max_steps, c_target=c_target)
    for ck in ckpts:
        entry = scores.get(ck.name, {})
        sig = file_signature(ck / MODEL_FILE)
        if entry.get("file") == sig and "digest" in entry:
            continue  # unchanged since it was scored: no reload, no rehash
        digest = _digest(run_dir, ck)
        if entry.get("digest") == digest:
            scores[ck.name] = {**entry, "file": sig}  # the same weights (e.g. a score file written before signatures)
            continue
        policy = load_policy(run_dir, bank, greedy=True, seed=seed, checkpoint=ck)
        summary = summarize(evaluate(bank, episodes, policy, config), config.min_optimal_length, protocol=protocol)
        state = read_json(ck / "state.json")["progress"]
        scores[ck.name] = {
            "update": int(state["update"]),
            "env_steps": int(state["env_steps"]),
            "episodes": int(state["episodes"]),
            "digest": digest,
            "file": sig,
            "metrics": summary,
        }
        progress(f"    {ck.name}: " + ", ".join(f"{k} {100 * summary['ALL'][k]:.1f}" for k in RANK_BY))
        atomic_write_json(
            path,
            {
                "episodes_file": str(Path(episodes_file).resolve()),
                "max_steps": max_steps,
                "c_target": c_target,
                "protocol": protocol,
                "scores": scores,
                "best": old.get("best") if same_list else None,
                "best_file": old.get("best_file"),
            },
        )
    live = {k: v for k, v in scores.items() if (run_dir / "checkpoints" / k).is_dir()}
    name = max(live, key=lambda k: (*(live[k]["metrics"]["ALL"][m] for m in RANK_BY), -live[k]["update"]))
    best = run_dir / BEST
    have = read_json(best / "state.json").get("selected_from") if (best / "state.json").exists() else None
    # RUN/best is rehashed only when it is not the folder this function last wrote or checked with these weights
    unchanged = (
        have == name
        and (best / MODEL_FILE).exists()
        and old.get("best_file") == {"file": file_signature(best / MODEL_FILE), "digest": live[name]["digest"]}
    )
    if not unchanged and (have != name or _digest(run_dir, best) != live[name]["digest"]):
        with atomic_folder(best) as tmp:
            for f in (run_dir / "checkpoints" / name).iterdir():
                if f.is_file():
                    shutil.copy2(f, tmp / f.name)
            st = read_json(tmp / "state.json")
            atomic_write_json(tmp / "state.json", {**st, "selected_from": name})
    result = {
        "episodes_file": str(Path(episodes_file).resolve()),
        "max_steps": max_steps,
        "c_target": c_target,
        "protocol": protocol,
        "scores": scores,
        "best": name,
        "best_file": {"file": file_signature(best / MODEL_FILE), "digest": live[name]["digest"]},
    }
    atomic_write_json(path, result)
    return result


def chosen(selection: dict) -> dict:
    """What a job or the demo records about the checkpoint a selection kept: its name, update, the number of
    checkpoints scored and its validation SR / SPL (fractions, ALL episodes)."""
    b = selection["scores"][selection["best"]]
    return {
        "name": selection["best"],
        "update": b["update"],
        "candidates": len(selection["scores"]),
        "val_SR": b["metrics"]["ALL"]["SR"],
        "val_SPL": b["metrics"]["ALL"]["SPL"],
    }


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--run", required=True, help="a `tsnav train` run folder")
    parser.add_argument("--data", required=True, help="dataset root holding the validation scenes")
    parser.add_argument("--episodes", required=True, help="validation episode list (`tsnav episodes --split val`)")
    parser.add_argument("--max-steps", type=int, default=100, help="episode length limit (paper: 100)")
    add_shared(
        parser,
        "protocol",
        default=None,
        help="success protocol (default: the episode list's); naming it lets a run trained under "
        "the other protocol be scored on this list",
    )


def run(args: argparse.Namespace) -> int:
    if not (Path(args.run) / "config.json").exists():
        raise CommandError(f"--run {args.run}: not a training run (no config.json)")
    if not Path(args.episodes).exists():
        raise CommandError(f"--episodes {args.episodes}: no such file")
    if args.max_steps < 1:
        raise CommandError("--max-steps must be >= 1")
    try:
        res = select_checkpoint(args.run, args.data, args.episodes, max_steps=args.max_steps, protocol=args.protocol)
    except (FileNotFoundError, ValueError) as e:
        raise CommandError(str(e)) from None
    b = res["scores"][res["best"]]
    print(
        f"{args.run}: best checkpoint {res['best']} (update {b['update']}; "
        + ", ".join(f"{k} {100 * b['metrics']['ALL'][k]:.1f}" for k in RANK_BY)
        + f", protocol {res['protocol']}) -> {Path(args.run) / BEST}"
    )
    return 0
