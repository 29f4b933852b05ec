"""``tsnav convergence``: train one agent in chunks of updates and score every chunk's checkpoint on
validation episodes, to find the budget at which the validation curve stops rising (issue 15, item 3: TSRM +
DE-MAE on the paper's 80 training rooms; its plateau sets the ``medium`` scale of the experiments).

    tsnav convergence --data WORLD --features NAME --detections NAME --out DIR [--updates 8000] [--chunk 250]
                      [--config RECIPE.toml] [--set SECTION.KEY=VALUE] [any setting of tsnav train]

The training settings are ``tsnav train``'s, made from the same fields (:mod:`tsnav.rl.recipe`), starting from
the ``medium`` scale's (:data:`CONVERGENCE_TRAIN`: batched A2C, the ``cpu`` network, lr 1e-3, 256 episodes per
update, 8000 updates); ``OUT/recipe.toml`` is the resolved recipe.

Resumable at any moment: the run folder ``OUT/run`` resumes from its last checkpoint (every chunk boundary is
a kept milestone), the scores of checkpoints already evaluated are kept in ``OUT/run/selection.json``
(:mod:`tsnav.eval.select`, which also keeps the best as ``OUT/run/best``), and the curve ``OUT/curve.png``
(validation SR / SPL / SSSPL / NSNPL against environment steps and against training episodes) and
``OUT/curve.json`` are rewritten after every chunk. The command stops at ``--updates`` or, with
``--patience P``, when validation SR has not risen for ``P`` chunks.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..agent.model import AgentConfig
from ..agent.observe import GROUND_TRUTH
from ..atomic import atomic_save_figure, atomic_write_json, atomic_write_text
from ..errors import CommandError
from ..metrics import curve_metrics
from ..eval.select import select_checkpoint
from ..rl.config import TrainConfig
from ..rl.recipe import SECTIONS as RUN_SECTIONS
from ..rl.recipe import add_recipe_options, add_run_options, recipe_from_args, resolve_run, run_recipe
from ..rl.train import train_run
from ..settings import add_options, add_shared, build, dump_recipe, to_recipe
from .config import SCALES
from .steps import ensure_episodes, episodes_name


def curve_points(selection: dict) -> list[dict]:
    """The scored checkpoints of a selection (:func:`select_checkpoint`), by update: update, env steps,
    episodes and the validation metrics drawn on curves (ALL episodes, fractions; ``Metric.curve`` of
    :mod:`tsnav.metrics`)."""
    pts = [
        {
            "update": v["update"],
            "env_steps": v["env_steps"],
            "episodes": v["episodes"],
            **{m: v["metrics"]["ALL"][m] for m in curve_metrics() if m in v["metrics"]["ALL"]},
        }
        for v in selection["scores"].values()
    ]
    return sorted(pts, key=lambda p: p["update"])


def plot_curve(points: list[dict], path: str | Path, title: str = "") -> Path:
    """Validation metrics (percent) against environment steps (left) and training episodes (right)."""
    fig = Figure(figsize=(11, 4.2))
    FigureCanvasAgg(fig)
    for ax, key, label in (
        (fig.add_subplot(1, 2, 1), "env_steps", "environment steps"),
        (fig.add_subplot(1, 2, 2), "episodes", "training episodes"),
    ):
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


def chunk_config(cfg: TrainConfig, end: int, chunk: int) -> TrainConfig:
    """The training configuration of the chunk that ends at update ``end``: ``cfg`` with that budget and a checkpoint
    kept every ``chunk`` updates. A learning-rate schedule keeps the horizon of the whole run (``cfg``'s ``updates``
    unless it names ``lr_decay_updates``), not the chunk's, so every chunk continues the same run."""
    horizon = {"lr_decay_updates": cfg.lr_horizon} if cfg.lr_schedule != "constant" else {}
    return TrainConfig.from_dict(
        {
            **cfg.to_dict(),
            **horizon,
            "updates": end,
            "episodes": None,
            "minutes": None,
            "checkpoint_every": chunk,
            "milestone_every": chunk,
        }
    )


def run_convergence(
    cfg: TrainConfig,
    agent: AgentConfig,
    out: str | Path,
    *,
    chunk: int,
    val_per_room_type: int = 50,
    patience: int | None = None,
    max_steps: int = 100,
    say=print,
    episodes: str | Path | None = None,
) -> list[dict]:
    """Train ``cfg`` (its ``updates`` the total) with network ``agent`` in chunks of ``chunk`` updates under
    ``OUT/run``, scoring each chunk's checkpoint on validation episodes (``val_per_room_type`` per room type drawn
    on the val rooms, or the list ``episodes`` when given); returns the curve points. Resumes whatever was done
    before."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    total = int(cfg.updates)
    val = episodes or ensure_episodes(
        cfg.data, "val", out / episodes_name("val", cfg.protocol), val_per_room_type, protocol=cfg.protocol
    )
    run = out / "run"
    points: list[dict] = []
    deviations = [f"distance increase x{cfg.distance_increase_scale:g}"] if cfg.distance_increase_scale != 1.0 else []
    deviations += ["mirror"] if cfg.mirror else []
    reward = cfg.reward_config()
    deviations += [f"K_r {reward.k_regret:g}"] if reward.uses("regret") else []
    deviations += [f"failed Done {reward.failed_done:g}"] if reward.failed_done else []
    deviations += ["blocked-action"] if agent.blocked_action else []
    deviations += ["mirror-symmetric policy"] if agent.mirror_policy else []
    deviations += ["memory history"] if agent.memory_history else []
    deviations += [f"lr {cfg.lr_schedule} to {cfg.lr_final:g}"] if cfg.lr_schedule != "constant" else []
    if agent.target_depth:
        deviations += ["TRUE target depth (a diagnostic)" if agent.target_depth == GROUND_TRUTH else "target depth"]
    for end in list(range(chunk, total, chunk)) + [total]:
        c = chunk_config(cfg, end, chunk)
        train_run(c, agent, run, progress_bar=False)
        sel = select_checkpoint(run, cfg.data, val, max_steps=max_steps, progress=say)
        points = curve_points(sel)
        atomic_write_json(
            out / "curve.json",
            {"points": points, "best": sel["best"], "chunk": chunk, "protocol": cfg.protocol, "train": c.to_dict()},
        )
        plot_curve(
            points,
            out / "curve.png",
            title=", ".join(
                [f"{cfg.reward} reward", f"features {cfg.features}", f"protocol {cfg.protocol}"] + deviations
            ),
        )
        last = points[-1]
        say(
            f"update {last['update']}: env steps {last['env_steps']}, episodes {last['episodes']}, "
            + ", ".join(f"val {m} {100 * last[m]:.1f}" for m in curve_metrics() if m in last)
            + f" (protocol {cfg.protocol})"
        )
        if plateaued(points, patience):
            say(f"validation SR has not risen for {patience} chunks: stopping at update {last['update']}")
            break
    return points


@dataclass
class ConvergenceConfig:
    """How ``tsnav convergence`` cuts its training into scored chunks (recipe section ``[convergence]``)."""

    chunk: int = 250
    """Updates between validation points (each chunk's checkpoint is scored on validation episodes)."""
    patience: int | None = None
    """Stop when validation SR has not risen for this many chunks (None: train to ``train.updates``)."""
    val_per_room_type: int = 50
    """Validation episodes per room type."""

    def __post_init__(self):
        for name in ("chunk", "val_per_room_type"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.patience is not None and self.patience < 1:
            raise ValueError(f"patience must be >= 1, got {self.patience}")


#: The training settings ``tsnav convergence`` starts from: the ``medium`` scale's (batched A2C, ``cpu`` network,
#: lr 1e-3, 256 episodes per update), whose budget this command measured, with 8000 updates in all.
CONVERGENCE_TRAIN = replace(SCALES["medium"].train, updates=8000, milestone_every=None)
#: TrainConfig fields this command sets itself (batched A2C, a budget in updates, a kept checkpoint per chunk).
CONVERGENCE_OWN = ("algo", "episodes", "minutes", "checkpoint_every", "milestone_every", "workers")
#: The sections of a convergence recipe.
SECTIONS = (*RUN_SECTIONS, "convergence")


def build_parser(parser: argparse.ArgumentParser) -> None:
    add_shared(parser, "out", required=True, help="output folder (resumed when it exists)")
    add_recipe_options(parser)
    add_options(parser.add_argument_group("chunks (recipe section [convergence])"), ConvergenceConfig, "convergence")
    add_run_options(parser, exclude_train=CONVERGENCE_OWN, defaults=CONVERGENCE_TRAIN)


def resolve(args: argparse.Namespace) -> tuple:
    """``(TrainConfig, AgentConfig, ConvergenceConfig)`` of the command line over :data:`CONVERGENCE_TRAIN`."""
    recipe = recipe_from_args(args, SECTIONS)
    conv = build(ConvergenceConfig, recipe.pop("convergence", {}), "convergence")
    recipe["train"] = {**to_recipe(CONVERGENCE_TRAIN), **recipe.get("train", {})}
    recipe["train"].pop("reward_settings", None)
    for need in ("data", "features", "detections"):
        if not recipe["train"].get(need):
            raise CommandError(f"--{need} is required")
    data = Path(recipe["train"]["data"])
    if not data.is_dir():
        raise CommandError(f"--data {data}: no such dataset folder")
    recipe["train"]["data"] = str(data.resolve())
    cfg, agent = resolve_run(recipe)
    if cfg.algo != "batched" or cfg.updates is None:
        raise CommandError("tsnav convergence trains with algo batched and a budget in updates")
    return cfg, agent, conv


def run(args: argparse.Namespace) -> int:
    cfg, agent, conv = resolve(args)
    atomic_write_text(
        Path(args.out) / "recipe.toml",
        dump_recipe(
            {**run_recipe(cfg, agent), "convergence": to_recipe(conv)},
            header="The resolved recipe of this convergence run (tsnav convergence --config FILE reruns it).",
        ),
    )
    run_convergence(
        cfg, agent, args.out, chunk=conv.chunk, val_per_room_type=conv.val_per_room_type, patience=conv.patience
    )
    print(f"curve: {Path(args.out) / 'curve.png'}, best checkpoint: {Path(args.out) / 'run' / 'best'}")
    return 0
