"""``tsnav convergence``: train one agent in chunks of updates and score every chunk's checkpoint on
validation episodes, to find the budget at which the validation curve stops rising (issue 15, item 3: TSRM +
DE-MAE on the paper's 80 training rooms; its plateau sets the ``medium`` scale of the experiments).

    tsnav convergence --data WORLD --features NAME --out DIR [--detections NAME] [--updates 8000]
                      [--chunk 250] [--num-envs 256] [--preset cpu] [--lr 1e-3] [--entropy-coef 0.01]
                      [--val-per-room-type 50]

Resumable at any moment: the run folder ``OUT/run`` resumes from its last checkpoint (every chunk boundary is
a kept milestone), the scores of checkpoints already evaluated are kept in ``OUT/run/selection.json``
(:mod:`tsnav.eval.select`, which also keeps the best as ``OUT/run/best``), and the curve ``OUT/curve.png``
(validation SR / SPL / SSSPL / NSNPL against environment steps and against training episodes) and
``OUT/curve.json`` are rewritten after every chunk. The command stops at ``--updates`` or, with
``--patience P``, when validation SR has not risen for ``P`` chunks.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..agent import agent_config
from ..atomic import atomic_save_figure, atomic_write_json
from ..errors import CommandError
from ..metrics import curve_metrics
from ..rl.config import PRECISIONS, TrainConfig
from ..rl.train import train_run
from ..eval.select import select_checkpoint
from .steps import ensure_episodes, episodes_name


def curve_points(selection: dict) -> list[dict]:
    """The scored checkpoints of a selection (:func:`select_checkpoint`), by update: update, env steps,
    episodes and the validation metrics drawn on curves (ALL episodes, fractions; ``Metric.curve`` of
    :mod:`tsnav.metrics`)."""
    pts = [{"update": v["update"], "env_steps": v["env_steps"], "episodes": v["episodes"],
            **{m: v["metrics"]["ALL"][m] for m in curve_metrics() if m in v["metrics"]["ALL"]}}
           for v in selection["scores"].values()]
    return sorted(pts, key=lambda p: p["update"])


def plot_curve(points: list[dict], path: str | Path, title: str = "") -> Path:
    """Validation metrics (percent) against environment steps (left) and training episodes (right)."""
    fig = Figure(figsize=(11, 4.2))
    FigureCanvasAgg(fig)
    for ax, key, label in ((fig.add_subplot(1, 2, 1), "env_steps", "environment steps"),
                           (fig.add_subplot(1, 2, 2), "episodes", "training episodes")):
        for m in (m for m in curve_metrics() if all(m in p for p in points)):  # scored before a metric was added
            ax.plot([p[key] for p in points], [100 * p[m] for p in points], marker="o", ms=3, label=m)
        ax.set_xlabel(label)
        ax.set_ylabel("validation, %")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    fig.axes[0].legend(loc="best")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return atomic_save_figure(fig, path, dpi=100)


def plateaued(points: list[dict], patience: int | None) -> bool:
    """Whether validation SR has not exceeded its earlier best for the last ``patience`` points."""
    if not patience or len(points) <= patience:
        return False
    best_before = max(p["SR"] for p in points[:-patience])
    return max(p["SR"] for p in points[-patience:]) <= best_before


def run_convergence(cfg: TrainConfig, preset: str, out: str | Path, *, chunk: int, val_per_room_type: int = 50,
                    patience: int | None = None, max_steps: int = 100, say=print,
                    agent_overrides: dict | None = None) -> list[dict]:
    """Train ``cfg`` (its ``updates`` the total) in chunks of ``chunk`` updates under ``OUT/run``, scoring each
    chunk's checkpoint on validation episodes; returns the curve points. Resumes whatever was done before.
    ``agent_overrides``: fields of the agent preset's :class:`~tsnav.agent.AgentConfig` to change."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    total = int(cfg.updates)
    val = ensure_episodes(cfg.data, "val", out / episodes_name("val", cfg.protocol), val_per_room_type,
                          protocol=cfg.protocol)
    run = out / "run"
    points: list[dict] = []
    deviations = ([f"distance increase x{cfg.distance_increase_scale:g}"] if cfg.distance_increase_scale != 1.0 else [])
    deviations += ["mirror"] if cfg.mirror else []
    deviations += ["blocked-action"] if (agent_overrides or {}).get("blocked_action") else []
    for end in list(range(chunk, total, chunk)) + [total]:
        c = TrainConfig.from_dict({**cfg.to_dict(), "updates": end, "episodes": None, "minutes": None,
                                   "checkpoint_every": chunk, "milestone_every": chunk})
        train_run(c, agent_config(preset, **(agent_overrides or {})), run, progress_bar=False)
        sel = select_checkpoint(run, cfg.data, val, max_steps=max_steps, progress=say)
        points = curve_points(sel)
        atomic_write_json(out / "curve.json", {"points": points, "best": sel["best"], "chunk": chunk,
                                               "protocol": cfg.protocol, "train": c.to_dict()})
        plot_curve(points, out / "curve.png", title=", ".join(
            [f"{cfg.reward} reward", f"features {cfg.features}", f"protocol {cfg.protocol}"] + deviations))
        last = points[-1]
        say(f"update {last['update']}: env steps {last['env_steps']}, episodes {last['episodes']}, "
            + ", ".join(f"val {m} {100 * last[m]:.1f}" for m in curve_metrics() if m in last)
            + f" (protocol {cfg.protocol})")
        if plateaued(points, patience):
            say(f"validation SR has not risen for {patience} chunks: stopping at update {last['update']}")
            break
    return points


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset root with train and val scenes")
    parser.add_argument("--features", required=True, help="feature cache name (features_<NAME>.hdf5, `tsnav features`)")
    parser.add_argument("--out", required=True, help="output folder (resumed when it exists)")
    parser.add_argument("--detections", required=True,
                        help="detection tables detections_<NAME>.hdf5 (`tsnav detect`), e.g. learned or oracle")
    parser.add_argument("--reward", default="tsrm", choices=["tsrm", "baseline", "explore", "distance"])
    parser.add_argument("--updates", type=int, default=8000, help="total updates (default 8000)")
    parser.add_argument("--chunk", type=int, default=250, help="updates between validation points (default 250)")
    parser.add_argument("--patience", type=int, default=None, help="stop when val SR has not risen for this many chunks")
    parser.add_argument("--num-envs", type=int, default=256, help="episodes per update (default 256)")
    parser.add_argument("--preset", default="cpu", help="agent size: cpu or paper (default cpu)")
    parser.add_argument("--lr", type=float, default=1e-3, help="learning rate (default 1e-3; paper 1e-4)")
    parser.add_argument("--entropy-coef", type=float, default=0.01,
                        help="weight of the entropy bonus (default 0.01, the lineage's)")
    parser.add_argument("--precision", default="fp32", choices=PRECISIONS,
                        help="rollout forward passes in float32 (default) or bfloat16 autocast")
    parser.add_argument("--procs", type=int, default=1,
                        help="CPU processes sharing each update's episodes (default 1; 2 uses both cores)")
    parser.add_argument("--max-steps", type=int, default=30,
                        help="training episode length in actions (default 30, the lineage's; the validation episodes "
                             "always allow 100, the paper's test length)")
    parser.add_argument("--blocked-action", action="store_true",
                        help="a deviation from the paper: the previous-action input tells a MoveAhead that left the "
                             "agent where it was (AgentConfig.blocked_action)")
    parser.add_argument("--mirror", action="store_true",
                        help="a deviation from the paper: also train on the mirror image of every training room "
                             "(TrainConfig.mirror; needs `tsnav features --mirror` and `tsnav detect --mirror`)")
    parser.add_argument("--distance-increase-scale", type=float, default=1.0,
                        help="a deviation from the paper when not 1.0 (the default): multiply the distance reward of "
                             "a step that increases the distance to the target by this "
                             "(TrainConfig.distance_increase_scale)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--val-per-room-type", type=int, default=50, help="validation episodes per room type")
    parser.add_argument("--protocol", default="paper",
                        help="success protocol of training and of the validation episodes: paper or lineage "
                             "(default: paper)")


def run(args: argparse.Namespace) -> int:
    if not Path(args.data).is_dir():
        raise CommandError(f"--data {args.data}: no such dataset folder")
    if args.updates < 1 or args.chunk < 1 or args.val_per_room_type < 1:
        raise CommandError("--updates, --chunk and --val-per-room-type must be >= 1")
    if not args.entropy_coef >= 0:
        raise CommandError(f"--entropy-coef must be >= 0, got {args.entropy_coef}")
    if args.max_steps < 1:
        raise CommandError(f"--max-steps must be >= 1, got {args.max_steps}")
    try:
        cfg = TrainConfig(data=str(Path(args.data).resolve()), features=args.features, detections=args.detections,
                          algo="batched", reward=args.reward, preset=args.preset, lr=args.lr, num_envs=args.num_envs,
                          seed=args.seed, updates=args.updates, entropy_coef=args.entropy_coef,
                          precision=args.precision, procs=args.procs, protocol=args.protocol,
                          max_steps=args.max_steps, mirror=args.mirror,
                          distance_increase_scale=args.distance_increase_scale)
        agent_config(args.preset)
        run_convergence(cfg, args.preset, args.out, chunk=args.chunk, val_per_room_type=args.val_per_room_type,
                        patience=args.patience, agent_overrides={"blocked_action": args.blocked_action})
    except (FileNotFoundError, ValueError) as e:
        raise CommandError(str(e)) from None
    print(f"curve: {Path(args.out) / 'curve.png'}, best checkpoint: {Path(args.out) / 'run' / 'best'}")
    return 0
