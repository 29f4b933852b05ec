"""The recipe of a shipped agent, and the steps that make the agent from it (``tsnav release make``).

A recipe (``configs/agents/<name>.toml``) names everything an agent is made with, one section per step:

==================  ======================================================================================
section             what
==================  ======================================================================================
``name``            the agent's name (the packed folder's)
``[world]``         the world preset and its rules version (:class:`WorldSettings`)
``[detections]``    the shipped detector whose tables drive the stage switch in training, and the one the packed
                    agent is evaluated with when another (:class:`DetectionSettings`)
``[pretrain]``      the encoder's pretraining (:class:`~tsnav.pretrain.train.PretrainConfig`)
``[features]``      the feature cache and the threads of the steps (:class:`FeatureSettings`)
``[train]``         training (:class:`~tsnav.rl.config.TrainConfig`; ``data``, ``features``, ``detections`` are
                    filled in), ``[reward]`` its reward's constants, ``[agent]`` its network
                    (:mod:`tsnav.rl.recipe`)
``[scoring]``       which episodes score the checkpoints in ``[convergence]`` and ``[select]``: the world's
                    val rooms, a fixed sample of the RoboTHOR challenge's train episodes, or none
                    (:class:`ScoringSettings`)
``[convergence]``   training in chunks scored on validation episodes (:class:`~tsnav.pipeline.convergence.
                    ConvergenceConfig`)
``[select]``        the milestones scored again on more validation episodes (:class:`SelectSettings`)
``[card]``          the model card's texts (summary, rooms, detector, budget, ...); its other fields (world,
                    detector and its fingerprint, protocol, encoder, the policy's update, the figures) are
                    written from the recipe and the run
==================  ======================================================================================

:func:`make_agent` runs the steps into a work folder: the world, the detector's tables, pretraining and the
feature cache, training in chunks (``tsnav convergence``), the second selection (``tsnav select``). Every step
resumes and is skipped when done. A RoboTHOR agent (``[world] preset = "robothor-real"``) is benchmarked on the
val scenes (:data:`~tsnav.pipeline.agent_steps.WORLD_EVAL`), so its checkpoints are scored on a sample of the
challenge's train episodes on the train scenes (``[scoring] episodes = "challenge-train"``) or not at all
(``"none"``: the last checkpoint is packed); a recipe scoring them on its val scenes is refused. Packing and the
evaluations that fill the card are :mod:`tsnav.pipeline.release`'s.
The recipe carries no machine path: the folders are the work folder's.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

from ..detect.shipped import DEFAULT_SHIPPED, SHIPPED, shipped_side
from ..distributed import set_threads
from ..errors import CommandError
from ..pretrain.train import PretrainConfig
from ..rl.recipe import SECTIONS as RUN_SECTIONS
from ..rl.recipe import resolve_run, run_recipe
from ..settings import build, to_recipe
from .convergence import ConvergenceConfig, run_convergence
from .agent_steps import WORLD_EVAL
from .steps import EncoderSpec, ensure_challenge_episodes, ensure_encoder, ensure_episodes, ensure_features, say

#: The sections of an agent's recipe (besides ``name``).
SECTIONS = ("world", "detections", "pretrain", "features", *RUN_SECTIONS, "scoring", "convergence", "select", "card")


@dataclass
class WorldSettings:
    """The world the agent is trained, selected and tested on (``tsnav world``)."""

    preset: str = "ithor-real"
    """World preset (``tsnav world --preset``): ``ithor-real``, the 120 real iTHOR rooms rebuilt from their recorded
    layouts (80 train, 20 val, 20 test); ``robothor-real``, RoboTHOR's 75 apartments (60 train, 15 val: the
    benchmark)."""
    version: int | None = None
    """Rules version of the world (``tsnav world --world-version``; None: the default)."""
    workers: int = 2
    """World-building processes (the same rooms for any number)."""
    infer_train_objects: bool = False
    """``robothor-real`` only: build the train apartments the way the val ones are (furniture from the plans,
    targets inferred from the challenge's train episodes; ``tsnav world --infer-train-objects``), so that the agent
    learns in apartments that look like its benchmark's. Reads the challenge's episode folder (``tsnav release make
    --challenge DIR`` or ``[scoring] challenge``)."""
    seed: int = 0
    """``robothor-real`` only: the draw of the train apartments' floor and wall materials (``tsnav world --seed``; 0,
    the benchmark's, one per apartment; any other seed draws them per scene). The val apartments keep 0's."""


@dataclass
class DetectionSettings:
    """The detection tables of the agent: those of a detector shipped with tsnav (:mod:`tsnav.detect.shipped`)."""

    shipped: str = DEFAULT_SHIPPED
    """The shipped detector whose per-class score drives the stage switch (C_target) and whose table feeds the
    target memory."""
    name: str = "learned"
    """Name of its tables, ``detections_<name>.hdf5`` (the run's ``train.detections``)."""
    evaluated: str = ""
    """The shipped detector the packed agent is evaluated with (its card's detector: ``tsnav release eval`` writes
    its tables, named after it, and the agent's target memory and the metrics' switch read them), when another than
    ``shipped`` (empty: ``shipped``): a detector trained after the agent, swapped in without training again. The
    card names both."""

    @property
    def card_shipped(self) -> str:
        """The shipped detector of the card (the one the agent is evaluated with)."""
        return self.evaluated or self.shipped

    @property
    def card_name(self) -> str:
        """Name of the card's tables."""
        return self.evaluated or self.name


@dataclass
class FeatureSettings:
    """The encoder's feature cache, and the torch threads of the steps."""

    encoder: str = "demae"
    """Id of the encoder (the feature cache is named ``<encoder>-<fingerprint>``; the card's ``encoder_id``)."""
    run: str = "demae-p16"
    """Folder of the pretraining run under ``WORK/pre``."""
    batch_size: int = 128
    """Frames per encoder call."""
    threads: int = 1
    """Torch CPU threads of pretraining, feature caching, training and selection (another count sums floats in
    another order: the shipped encoders were pretrained and cached on one)."""


#: Where the checkpoints' scoring episodes come from (:class:`ScoringSettings`).
SCORING_EPISODES = ("val", "challenge-train", "none")


@dataclass
class ScoringSettings:
    """Which episodes score the run's checkpoints: the ``[convergence]`` chunks and the ``[select]`` step."""

    episodes: str = "val"
    """``val``: episodes drawn on the world's val rooms (``tsnav episodes --split val``; the iTHOR agents, benchmarked
    on the test rooms); ``challenge-train``: fixed samples of the RoboTHOR challenge's train episodes converted on
    the train scenes (``tsnav thor challenge-episodes --split train``), ``[convergence] val_per_room_type`` of them
    drawn with seed 0 and ``[select] per_room_type`` with ``[select] seed`` (the apartments are one room type: these
    are the samples' sizes); ``none``: nothing scored, training runs to its budget and its last checkpoint is
    packed."""
    challenge: str = ""
    """The challenge's episode folder holding ``train/`` (robothor-challenge's ``dataset/``, e.g.
    ``../shared/robothor/challenge_episodes``; its train episodes are not packaged with tsnav), read by
    ``challenge-train``; ``tsnav release make --challenge DIR`` gives it instead."""
    chunks: bool = True
    """Score every ``[convergence]`` chunk while training (its patience may stop training early); false: train to
    the budget in one go, keeping a milestone every ``train.milestone_every`` updates, and let ``[select]`` score
    them."""

    def __post_init__(self):
        if self.episodes not in SCORING_EPISODES:
            raise ValueError(f"episodes must be one of {', '.join(SCORING_EPISODES)}, got {self.episodes!r}")


@dataclass
class SelectSettings:
    """The milestones of the run scored again on more validation episodes after training (``tsnav select`` in a
    copy of the run, ``WORK/conv/run-select``, whose best is packed)."""

    per_room_type: int | None = None
    """Validation episodes per room type (None: no second selection; the training's own best is packed)."""
    seed: int = 1
    """Seed of those episodes (another than the training's validation episodes, seed 0)."""


@dataclass
class AgentRecipe:
    """A resolved agent recipe (see the module docstring)."""

    name: str
    world: WorldSettings = field(default_factory=WorldSettings)
    detections: DetectionSettings = field(default_factory=DetectionSettings)
    pretrain: PretrainConfig = field(default_factory=PretrainConfig)
    features: FeatureSettings = field(default_factory=FeatureSettings)
    run: tuple = ()
    """``(TrainConfig, AgentConfig)`` of training (its data and features are the work folder's)."""
    scoring: ScoringSettings = field(default_factory=ScoringSettings)
    convergence: ConvergenceConfig = field(default_factory=ConvergenceConfig)
    select: SelectSettings = field(default_factory=SelectSettings)
    card: dict = field(default_factory=dict)

    def to_recipe(self) -> dict:
        """The resolved recipe (what ``recipe.toml`` beside the work and the packed agent holds)."""
        run = run_recipe(*self.run)
        for k in ("data", "features"):  # the work folder's
            run["train"].pop(k, None)
        return {
            "name": self.name,
            "world": to_recipe(self.world),
            "detections": to_recipe(self.detections),
            "pretrain": to_recipe(self.pretrain),
            "features": to_recipe(self.features),
            **run,
            "scoring": to_recipe(self.scoring),
            "convergence": to_recipe(self.convergence),
            "select": to_recipe(self.select),
            "card": self.card,
        }


def resolve_agent(recipe: dict, work: Path) -> AgentRecipe:
    """The :class:`AgentRecipe` of a recipe's sections, its training run on the work folder's world."""
    unknown = sorted(set(recipe) - {"name", *SECTIONS})
    if unknown:
        raise CommandError(
            f"no section {', '.join(unknown)} in an agent's recipe (sections: name, {', '.join(SECTIONS)})"
        )
    name = recipe.get("name")
    if not isinstance(name, str) or not name or "/" in name:
        raise CommandError('the recipe names no agent (name = "tsrm-demae-...")')
    det = build(DetectionSettings, recipe.get("detections"), "detections")
    for key in ("shipped", "evaluated"):
        value = getattr(det, key)
        if value and value not in SHIPPED:
            raise CommandError(
                f"[detections]: {key} {value!r} is no shipped detector (shipped: {', '.join(sorted(SHIPPED))})"
            )
    feats = build(FeatureSettings, recipe.get("features"), "features")
    train = dict(recipe.get("train") or {})
    for k in ("data", "features"):
        if k in train:
            raise CommandError(f"[train]: {k} is the work folder's, not the recipe's")
    if train.get("detections", det.name) != det.name:
        raise CommandError(
            f"[train]: detections {train['detections']!r} is not the tables of [detections] ({det.name!r})"
        )
    train.update(data=str((work / "world").resolve()), features="(cached in the features step)", detections=det.name)
    run = resolve_run({**{s: recipe.get(s) or {} for s in RUN_SECTIONS}, "train": train})
    if run[0].algo != "batched" or (run[0].updates is None and run[0].episodes is None):
        raise CommandError("[train]: an agent is made with algo batched and a budget in updates or episodes")
    card = recipe.get("card") or {}
    if not isinstance(card, dict) or not card.get("summary"):
        raise CommandError("[card]: the model card needs at least a summary")
    world = build(WorldSettings, recipe.get("world"), "world")
    scoring = build(ScoringSettings, recipe.get("scoring"), "scoring")
    select = build(SelectSettings, recipe.get("select"), "select")
    bench = WORLD_EVAL.get(world.preset, {}).get("eval_split", "test")
    if scoring.episodes == "val" and bench == "val":
        raise CommandError(
            f'[scoring]: episodes "val" would choose checkpoints on the {world.preset} val scenes, its benchmark: '
            f'use "challenge-train" (a sample of the challenge\'s train episodes) or "none" (the last checkpoint)'
        )
    if world.seed < 0 or (world.seed and world.preset != "robothor-real"):
        raise CommandError(
            f"[world]: seed {world.seed}: a seed of 0 or more, and one other than 0 for robothor-real only"
        )
    if world.infer_train_objects and world.preset != "robothor-real":
        raise CommandError(f"[world]: infer_train_objects applies to the robothor-real world, not {world.preset!r}")
    if world.infer_train_objects and scoring.episodes != "challenge-train":
        raise CommandError(
            "[world]: infer_train_objects reads the challenge's train episodes: it goes with [scoring] episodes = "
            '"challenge-train", which names their folder'
        )
    if scoring.episodes == "challenge-train" and not world.preset.startswith("robothor"):
        raise CommandError(f'[scoring]: episodes "challenge-train" are RoboTHOR\'s, not of the {world.preset} world')
    if run[0].updates is None and scoring.episodes != "none" and scoring.chunks:
        raise CommandError("[train]: training in chunks ([scoring] chunks = true) needs a budget in updates")
    if scoring.episodes != "none" and not scoring.chunks:
        if run[0].milestone_every is None:
            raise CommandError("[scoring]: chunks = false needs train.milestone_every (the milestones [select] scores)")
        if select.per_room_type is None:
            raise CommandError("[scoring]: chunks = false needs [select] per_room_type (nothing else scores them)")
    return AgentRecipe(
        name=name,
        world=world,
        detections=det,
        pretrain=build(PretrainConfig, recipe.get("pretrain"), "pretrain"),
        features=feats,
        run=run,
        scoring=scoring,
        convergence=build(ConvergenceConfig, recipe.get("convergence"), "convergence"),
        select=select,
        card=dict(card),
    )


@dataclass
class MadeAgent:
    """What :func:`make_agent` leaves in the work folder: the world, the run whose best is packed, the
    pretraining run."""

    world: Path
    run: Path
    encoder_run: Path
    features: str
    last: bool = False
    """Pack the run's last checkpoint, not its ``best`` (``[scoring] episodes = "none"``: nothing chose one)."""

    @property
    def checkpoint(self) -> Path:
        """The checkpoint folder to pack."""
        if not self.last:
            return self.run / "best"
        from ..rl.checkpoint import latest_checkpoint

        ck = latest_checkpoint(self.run)
        if ck is None:
            raise CommandError(f"{self.run}: no checkpoint to pack")
        return ck


def challenge_folder(r: AgentRecipe, challenge: str | Path | None = None) -> Path | None:
    """The challenge's episode folder that ``[scoring] episodes = "challenge-train"`` reads: ``challenge`` (``tsnav
    release make --challenge``), else the recipe's ``scoring.challenge``; a one-line error when neither names a
    folder holding ``train/*.json.gz``. None for the other scorings."""
    if r.scoring.episodes != "challenge-train":
        return None
    folder = challenge or r.scoring.challenge
    if not folder:
        raise CommandError(
            '[scoring]: episodes "challenge-train" reads the challenge\'s train episodes, which tsnav does not '
            "package: give their folder with --challenge DIR (holding train/, e.g. "
            "../shared/robothor/challenge_episodes) or scoring.challenge"
        )
    if not any((Path(folder) / "train").glob("*.json.gz")):
        raise CommandError(f"--challenge {folder}: no train/*.json.gz (the challenge's episode folder holds train/)")
    return Path(folder)


def make_agent(r: AgentRecipe, work: Path, *, until: str = "select", challenge: str | Path | None = None) -> MadeAgent:
    """Run the steps of recipe ``r`` in ``work`` up to ``until`` (:data:`STEPS`), each resumed or skipped when
    done; ``challenge``: the challenge's episode folder (:func:`challenge_folder`)."""
    from ..data.reader import list_scenes
    from ..world.build import BuildConfig, build_dataset

    world = work / "world"
    set_threads(r.features.threads)
    say(f"world {r.world.preset} -> {world}")
    overrides: dict = {"world_version": r.world.version} if r.world.version is not None else {}
    if r.world.seed:
        overrides["seed"] = r.world.seed
    if r.world.infer_train_objects:
        from ..world.presets import preset_scenes
        from ..world.robothor_real import missing_train_episodes

        overrides["infer_train"] = str(challenge_folder(r, challenge).resolve())
        why = missing_train_episodes(overrides["infer_train"], preset_scenes(r.world.preset))
        if why:
            raise CommandError(f"[world] infer_train_objects: {why}")
    cfg = BuildConfig.from_preset(r.world.preset, **overrides)
    build_dataset(world, r.world.preset, None, cfg, workers=r.world.workers)
    side, frames = shipped_side(r.detections.shipped), None
    if side != cfg.image_size:  # a detector that reads finer frames: the same rooms at its side, for it alone
        frames = work / f"world-{side}px"
        say(f"world at {side} px (the frames of the shipped detector {r.detections.shipped}) -> {frames}")
        at = BuildConfig.from_preset(r.world.preset, image_size=side, **overrides)
        build_dataset(frames, r.world.preset, None, at, workers=r.world.workers)
    if until == "world":
        return MadeAgent(world, work / "conv" / "run", work / "pre" / r.features.run, "")
    ensure_shipped_tables(world, r.detections, frames)
    if until == "detections":
        return MadeAgent(world, work / "conv" / "run", work / "pre" / r.features.run, "")
    pre = r.pretrain
    es = EncoderSpec(
        r.features.encoder, str(work / "pre" / r.features.run), pre.model, pre.patch_size, pre.img_size, pre
    )
    ensure_encoder(es, world)
    splits = [s for s in ("train", "val", "test") if list_scenes(world, s)]  # RoboTHOR has no test split
    features = ensure_features(es, world, splits, batch_size=r.features.batch_size, device=pre.device)
    made = MadeAgent(world, work / "conv" / "run", work / "pre" / r.features.run, features)
    if until == "features":
        return made
    from dataclasses import replace

    cfg, agent = r.run
    cfg = replace(cfg, features=features)
    conv, sc = r.convergence, r.scoring
    folder = challenge_folder(r, challenge)
    if sc.episodes == "none" or not sc.chunks:
        from ..rl.train import train_run

        say(
            f"train {r.name} -> {made.run} (to update {cfg.updates}; checkpoints scored "
            + ("never: the last is packed)" if sc.episodes == "none" else "after training by [select])")
        )
        train_run(cfg, agent, made.run, progress_bar=False)
        if sc.episodes == "none":
            return replace(made, last=True)
    else:
        scored = None
        if sc.episodes == "challenge-train":
            scored = ensure_challenge_episodes(
                world,
                "train",
                work / "conv" / f"train_challenge_{cfg.protocol}.json",
                cfg.protocol,
                challenge=folder,
                per_room_type=conv.val_per_room_type,
                seed=0,
            )
        run_convergence(
            cfg,
            agent,
            work / "conv",
            chunk=conv.chunk,
            val_per_room_type=conv.val_per_room_type,
            patience=conv.patience,
            episodes=scored,
        )
    if until == "train" or r.select.per_room_type is None:
        return made
    copy = select_again(made.run, world, cfg.protocol, r.select, work, folder)
    return MadeAgent(world, copy, made.encoder_run, features)


def ensure_shipped_tables(world: Path, det: DetectionSettings, frames: Path | None = None) -> None:
    """The shipped detector's tables in every room of ``world`` (those made already by it are kept; a table of
    another detector under the name is refused). A detector that reads other frames than ``world``'s reads the
    rooms built at its side in ``frames``, and its boxes are scaled to ``world``'s frames."""
    from ..data.reader import list_scenes, load_scene
    from ..detect.shipped import shipped_detector
    from .detector_steps import learned_tables, write_learned_tables

    have, _ = learned_tables(world, det.name)
    if any(fp is None for fp in have.values()):
        size = shipped_side(det.shipped) if frames is not None else load_scene(list_scenes(world)[0]).image_size
        model = shipped_detector(size, det.shipped)
        write_learned_tables(
            world, det.name, model, say=say, source=f"the shipped detector {det.shipped}", frames=frames
        )


def select_again(
    run: Path, world: Path, protocol: str, sel: SelectSettings, work: Path, challenge: Path | None = None
) -> Path:
    """Score every milestone of ``run`` on ``sel.per_room_type`` validation episodes per room type (seed
    ``sel.seed``) in a copy of it, ``RUN-select`` (the run keeps the training's own selection); returns the copy.
    With ``challenge`` (the challenge's episode folder), the episodes are a sample of the challenge's train
    episodes on the train scenes instead (``[scoring] episodes = "challenge-train"``)."""
    from ..eval.select import select_checkpoint

    if challenge is not None:
        episodes = ensure_challenge_episodes(
            world,
            "train",
            work / f"train_challenge_select_{protocol}.json",
            protocol,
            challenge=challenge,
            per_room_type=sel.per_room_type,
            seed=sel.seed,
        )
    else:
        episodes = ensure_episodes(
            world, "val", work / f"val_select_{protocol}.json", sel.per_room_type, seed=sel.seed, protocol=protocol
        )
    copy = run.with_name(run.name + "-select")
    if not copy.exists():
        tmp = copy.with_name(copy.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        shutil.copytree(run, tmp)
        tmp.rename(copy)
    select_checkpoint(copy, world, episodes)
    return copy
