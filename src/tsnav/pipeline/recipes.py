"""Recipes of experiments: an :class:`~tsnav.pipeline.config.ExperimentConfig` (``[experiment]``) and the
:class:`~tsnav.pipeline.config.ScaleConfig` its jobs are trained at (``[scale]``, with ``[scale.pretrain]``,
``[scale.train]``, ``[scale.detector]``, ``[scale.detector_model]``), as one TOML file (:mod:`tsnav.settings`).

``[scale]`` starts from the named scale (``experiment.scale``, one of
:data:`~tsnav.pipeline.config.SCALES`) and sets what it names, so a recipe may spell the whole scale out (the
files under ``configs/experiments/`` do, so that one file names everything an experiment is trained with) or
change one setting of it. ``tsnav experiment NAME ... --print-recipe`` prints the resolved recipe of a command
line; ``tsnav experiment FILE`` runs a recipe; ``OUT/recipe.toml`` is the resolved recipe of every experiment
folder.
"""

from __future__ import annotations

from pathlib import Path

from ..atomic import atomic_write_text
from ..errors import CommandError
from ..settings import build, dump_recipe, to_recipe
from .config import SCALES, ExperimentConfig, ScaleConfig

#: The sections of an experiment's recipe.
SECTIONS = ("experiment", "scale")
#: ExperimentConfig fields that name this machine's folders: given on the command line, left out of the recipe
#: files that ship (``configs/``), written into the resolved ``OUT/recipe.toml``.
#: Fields of ``[scale.train]`` that every job sets itself (from the experiment, its row and seed:
#: :func:`tsnav.pipeline.experiment.train_config_for`), left out of the recipe.
JOB_FIELDS = ("data", "features", "detections", "split", "reward", "seed", "c_target", "protocol", "device")
PATH_FIELDS = (
    "data",
    "out",
    "pretrain_dir",
    "detector_dir",
    "train_data",
    "vc1_weights",
    "resnet18_weights",
    "reuse_from",
)


def resolve_experiment(recipe: dict, *, need_paths: bool = True) -> tuple[ExperimentConfig, ScaleConfig]:
    """The experiment and its scale from ``recipe`` (one-line CommandError for bad keys or values; ``need_paths``:
    ``data`` and ``out`` must be set)."""
    unknown = sorted(set(recipe) - set(SECTIONS))
    if unknown:
        raise CommandError(
            f"no section {', '.join(unknown)} in an experiment's recipe (sections: {', '.join(SECTIONS)})"
        )
    exp = dict(recipe.get("experiment") or {})
    for need in ("experiment", "data", "out") if need_paths else ("experiment",):
        if not exp.get(need):
            raise CommandError(
                f"--{need} is required"
                if need != "experiment"
                else 'the recipe names no experiment ([experiment] experiment = "ablation", ...)'
            )
    exp.setdefault("data", "")
    exp.setdefault("out", "")
    cfg = build(
        ExperimentConfig, exp, "experiment", base=ExperimentConfig(experiment=str(exp["experiment"]), data="", out="")
    )
    if cfg.scale not in SCALES:
        raise CommandError(f"--scale {cfg.scale}: no such scale (choose from {', '.join(SCALES)})")
    scale = build(ScaleConfig, recipe.get("scale") or {}, "scale", base=SCALES[cfg.scale])
    return cfg, scale


def experiment_recipe(cfg: ExperimentConfig, scale: ScaleConfig, *, paths: bool = True) -> dict:
    """The resolved recipe of an experiment (``paths``: with the machine's folders, else without them)."""
    exp = to_recipe(cfg)
    if not paths:
        exp = {k: v for k, v in exp.items() if k not in PATH_FIELDS}
    sc = to_recipe(scale)
    sc["train"] = {k: v for k, v in sc["train"].items() if k not in JOB_FIELDS}
    return {"experiment": exp, "scale": sc}


def write_recipe(folder: str | Path, cfg: ExperimentConfig, scale: ScaleConfig, command: str) -> Path:
    """``FOLDER/recipe.toml``: the resolved recipe of an experiment (``command``: what wrote it)."""
    p = Path(folder) / "recipe.toml"
    atomic_write_text(p, dump_recipe(experiment_recipe(cfg, scale), header=f"The resolved recipe ({command})."))
    return p


def same_scale(a: ScaleConfig, b: ScaleConfig) -> bool:
    """Whether two scales are equal setting by setting (tuples and lists alike)."""
    return to_recipe(a) == to_recipe(b)
