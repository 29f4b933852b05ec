"""The paper's experiments as data: scales, rows, and the resolved configuration of an experiment.

A row is one line of a paper table (Table II ablation, Table III pretraining) or one point of Fig. 4
(threshold); :func:`experiment_rows` lists them. The jobs that run them live in :mod:`tsnav.pipeline.experiment`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar

import numpy as np

from ..constants import C_TARGET
from ..detect.train import DetectorTrainConfig
from ..metrics import METRICS
from ..protocol import PROTOCOLS
from ..pretrain.train import PretrainConfig
from ..rl.config import TrainConfig

#: The paper's experiments (``tsnav experiment``).
EXPERIMENTS = ("ablation", "pretraining", "threshold")
#: The demo's experiment (``tsnav demo``): the last row of Table II, TSRM + DE-MAE, at the ``demo`` scale.
DEMO = "demo"

#: Training updates of the demo's agent on the longer demo's worlds (``demo-real``, ``demo``; 64 episodes x 30 steps
#: each, one process of one thread): the same table on any machine. About 7 minutes on an idle 2-core machine
#: (417 s with checkpoint selection in `make demo` at main b6fda99, 2026-12-03).
DEMO_UPDATES = 1000
#: The quick demo (``tsnav demo`` on its default world, ``demo-real-small``), sized so that its steps take at most
#: 5 minutes of an idle 2-core machine (issue 26): DE-MAE for ``QUICK_DEMO_PRETRAIN_STEPS`` steps, then
#: ``QUICK_DEMO_UPDATES`` updates of ``QUICK_DEMO_ENVS`` episodes shared by ``QUICK_DEMO_PROCS`` processes (both
#: cores: 64 episodes per process cost one process's 64, so an update holds twice the episodes in the same time),
#: a milestone every ``QUICK_DEMO_MILESTONES`` updates.
QUICK_DEMO_PRETRAIN_STEPS = 200
QUICK_DEMO_UPDATES = 300
QUICK_DEMO_ENVS = 128
QUICK_DEMO_PROCS = 2
QUICK_DEMO_MILESTONES = 100
#: The quick demo's world preset (``tsnav demo``'s default).
QUICK_DEMO_PRESET = "demo-real-small"
#: Updates per job of the ``medium`` scale (256 episodes x 30 steps each = 7680 env steps per update; 2000
#: updates = 15.4 M env steps, about 0.68 M training episodes). Measured with `tsnav convergence` on the 80
#: ``ithor-real`` train rooms (TSRM + DE-MAE, learned switch, lr 1e-3, 400 greedy val episodes, docs/RESULTS.md
#: "Convergence on the 80 real rooms"): val SR 24.5 / 27.8 / 34.8 / 37.2 / 33.8 at updates 500 / 1000 / 1500 /
#: 2000 / 2250, i.e. flat within its standard error (~2.4 points) from 1500 on. At the paper's lr 1e-4 the same
#: run needs ~3500 updates to reach a lower plateau (SR 29). Milestones every 250 updates are scored on val.
MEDIUM_UPDATES = 2000
#: The learned detector of the 128-px worlds (``ithor-real``): space-to-depth stem 2, the wider backbone and the
#: fine grid that ``tsnav detect`` gives a new 128-px checkpoint (:func:`tsnav.detect.model.default_config`,
#: BENCHMARKS.md "Learned detector"); the 64-px scales keep ``DetectorConfig``'s defaults with stem 1.
DETECTOR_128 = {"stem": 2, "widths": (32, 64, 128), "fine": True}
#: Detector training steps of the 128-px scales (:func:`tsnav.detect.train.default_train_steps`).
DETECTOR_128_STEPS = 9000


def _pretrain() -> PretrainConfig:
    """Pretraining of the ``small`` scale: ViT-Tiny at 64x64, 800 steps of 64 images, a larger learning rate
    (1.5e-3 per 256 images) than MAE's for short CPU runs. ``method`` and ``device`` are the job's."""
    return PretrainConfig(model="vit_tiny", patch_size=16, img_size=64, steps=800, batch_size=64, base_lr=1.5e-3)


def _train() -> TrainConfig:
    """Agent training of the ``small`` scale: batched A2C over 64 episodes of the ``cpu`` network, lr 1e-3
    (paper: 1e-4 for 14 A3C workers of one episode each; on the 80 real rooms 1e-3 reached a higher validation
    plateau in a third of the updates, docs/RESULTS.md "Convergence on the 80 real rooms"), 1000 updates per job
    (about 1.9 M environment steps), a milestone every 200 updates for validation-based selection (issue 15).
    The job fills in its data, features, detections, reward, seed, C_target and protocol."""
    return TrainConfig(
        algo="batched", preset="cpu", lr=1e-3, num_envs=64, procs=1, workers=14, updates=1000, milestone_every=200
    )


def _detector() -> DetectorTrainConfig:
    """The learned detector's training (issue 14 item 4): 2500 steps of 64 frames on one torch thread (a budget
    in steps, so the same detector on a busy and an idle machine)."""
    return DetectorTrainConfig(steps=2500, batch_size=64, max_states_per_scene=None, threads=1)


@dataclass
class ScaleConfig:
    """Sizes of every pipeline step at one scale (``small``: 2-core CPU; ``paper``: the paper's settings): the
    configurations of the three trainers, and the sizes of the steps around them. A scale that differs from
    another says so with :meth:`override` (``dataclasses.replace`` of the nested configurations); each job
    completes its trainer's configuration with ``dataclasses.replace`` too (:func:`tsnav.pipeline.steps.encoder_spec`,
    :func:`tsnav.pipeline.experiment.train_config_for`, :func:`tsnav.pipeline.detector_steps.detector_configs`)."""

    pretrain: PretrainConfig = field(default_factory=_pretrain)
    """Pretraining of the MAE-family encoders (and of the supervised ResNet18 baseline, with
    ``resnet_pretrain_steps`` and MAE's own learning rate). ``steps`` None: ``epochs`` passes over the data."""
    train: TrainConfig = field(default_factory=_train)
    """Agent training per job: trainer, network preset, lr, episodes per update (``num_envs``), processes
    (``procs``: part of the agent's identity), A3C ``workers``, the budget (``updates``, ``episodes``; ``minutes``
    only when asked for, the result then depends on the machine's load; none: the paper's 1.5 M episodes) and
    ``milestone_every`` (None: selection among the two newest checkpoints)."""
    detector: DetectorTrainConfig = field(default_factory=_detector)
    """The learned detector's training, when the dataset lacks learned tables (``max_states_per_scene``: random
    states per train room; None: every state)."""
    detector_model: dict = field(default_factory=lambda: {"stem": 1})
    """:class:`~tsnav.detect.model.DetectorConfig` fields of a new detector besides the input side (taken from the
    train frames): 64-px worlds use ``stem`` 1, 128-px worlds ``stem`` 2 (space-to-depth: a 128-px frame then costs
    what a 64-px one does)."""
    resnet_pretrain_steps: int | None = 400
    """Optimiser steps of the supervised ResNet18 baseline (used when no ImageNet weights are given); None: as
    ``pretrain.steps``."""
    feature_batch_size: int = 128
    """Frames per encoder call when caching features."""
    test_per_room_type: int = 250
    """Test episodes per room type (the lineage: 250)."""
    val_per_room_type: int = 100
    """Validation episodes per room type (threshold sweep, checkpoint selection)."""
    max_steps: int = 100
    """Evaluation episode length (paper: 100)."""
    world: str = "demo"
    """World preset (``tsnav world --preset``) the scale runs on: built into ``--data`` when that folder does not
    exist yet. Paper: ``ithor-real``, the real iTHOR scenes rebuilt from their recorded layouts."""
    agent: dict = field(default_factory=dict)
    """:class:`~tsnav.agent.model.AgentConfig` fields of every job's network over the ``train.preset`` preset (e.g.
    ``dropout``, paper IV-A: 0.45); empty: the preset's."""

    def override(
        self, pretrain: dict | None = None, train: dict | None = None, detector: dict | None = None, **fields
    ) -> "ScaleConfig":
        """A copy with fields of the nested configurations (``pretrain``, ``train``, ``detector``: field -> value)
        and of the scale itself replaced (``dataclasses.replace``, so every configuration checks its values)."""
        return replace(
            self,
            **fields,
            **{
                k: replace(getattr(self, k), **v)
                for k, v in (("pretrain", pretrain), ("train", train), ("detector", detector))
                if v
            },
        )

    @property
    def budget(self) -> dict:
        """The training budget per job as the demo's markers record it: updates, minutes, episodes."""
        return {"updates": self.train.updates, "minutes": self.train.minutes, "episodes": self.train.episodes}


def demo_scale(preset: str) -> "ScaleConfig":
    """The demo's sizes on world ``preset``: ``SCALES["demo"]``, with the quick demo's shorter training
    (:data:`QUICK_DEMO_UPDATES`) on its rooms (:data:`QUICK_DEMO_PRESET`)."""
    if preset == QUICK_DEMO_PRESET:
        return SCALES["demo"].override(
            pretrain=dict(steps=QUICK_DEMO_PRETRAIN_STEPS),
            train=dict(
                updates=QUICK_DEMO_UPDATES,
                num_envs=QUICK_DEMO_ENVS,
                procs=QUICK_DEMO_PROCS,
                milestone_every=QUICK_DEMO_MILESTONES,
            ),
        )
    return SCALES["demo"]


#: Where missing learned detection tables come from (``ExperimentConfig.detector``, ``DemoConfig.detector``):
#: a detector trained here, or the one shipped in the package (:mod:`tsnav.detect.shipped`).
DETECTOR_SOURCES = ("train", "shipped")


#: The four scales. ``demo``: the scale of ``tsnav demo`` (its one row in about ten minutes); ``small``: a 2-core
#: CPU in about two hours; ``medium``: the budget at which TSRM + DE-MAE's validation curve on the 80 training
#: rooms has plateaued (issue 15, items 3-4; MEDIUM_UPDATES); ``paper``: the paper's settings.
SMALL = ScaleConfig()
SCALES = {
    "demo": SMALL.override(pretrain=dict(steps=300), train=dict(updates=DEMO_UPDATES), test_per_room_type=100),
    "small": SMALL,
    "medium": SMALL.override(
        train=dict(updates=MEDIUM_UPDATES, milestone_every=250, num_envs=256),
        detector=dict(steps=DETECTOR_128_STEPS, max_states_per_scene=1600),
        test_per_room_type=250,
        val_per_room_type=100,
        world="ithor-real",
        detector_model=dict(DETECTOR_128),
    ),
    "paper": SMALL.override(
        pretrain=dict(model="vit_base", patch_size=16, img_size=224, steps=None, batch_size=64, base_lr=None),
        train=dict(
            algo="a3c",
            preset="paper",
            lr=1e-4,
            num_envs=16,
            workers=14,
            updates=None,
            episodes=1_500_000,
            milestone_every=None,
        ),
        detector=dict(steps=DETECTOR_128_STEPS, max_states_per_scene=1600),
        feature_batch_size=64,
        test_per_room_type=250,
        val_per_room_type=250,
        world="ithor-real",
        detector_model=dict(DETECTOR_128),
    ),
}


@dataclass
class Row:
    """One row of an experiment's table (one trained agent per seed)."""

    id: str
    """Short name, used in folder names."""
    label: str
    """What the table shows."""
    encoder: str
    """Encoder of the image features: ``resnet18``, ``demae``, ``mae``, ``demae-crop`` or ``vc1``."""
    reward: str
    """Reward variant (:data:`tsnav.tsrm.reward.VARIANTS`)."""
    c_target: float = C_TARGET
    """Stage-switch threshold for training and evaluation (paper: 0.7)."""
    flags: dict = field(default_factory=dict)
    """Check-mark columns of the table (Table II: exploration reward, distance reward, DE-MAE)."""
    detections: str | None = None
    """Detection table of this row's agent and stage switch when it is not the experiment's
    (:attr:`ExperimentConfig.detections`): the ablation's oracle-switch row reads ``oracle``."""

    def detections_of(self, default: str) -> str:
        """The detection table name this row trains and is evaluated with."""
        return self.detections or default


ABLATION_FLAGS = ("Exploration Reward", "Distance Reward", "DE-MAE")


def _abl(id_, label, enc, reward, e, d, m) -> Row:
    return Row(id_, label, enc, reward, C_TARGET, dict(zip(ABLATION_FLAGS, (e, d, m))))


def experiment_rows(name: str, vc1: bool = False) -> list[Row]:
    """The rows of an experiment (paper Table II, Table III, Fig. 4)."""
    if name == "ablation":
        return [
            _abl("baseline", "baseline (ResNet18, baseline reward)", "resnet18", "baseline", 0, 0, 0),
            _abl("explore", "+ exploration reward", "resnet18", "explore", 1, 0, 0),
            _abl("distance", "+ distance reward", "resnet18", "distance", 0, 1, 0),
            _abl("tsrm", "+ both (TSRM)", "resnet18", "tsrm", 1, 1, 0),
            _abl("demae", "+ DE-MAE alone", "demae", "baseline", 0, 0, 1),
            _abl("tsrm_demae", "TSRM + DE-MAE", "demae", "tsrm", 1, 1, 1),
            # issue 14 item 4: the same agent with the oracle's table (no distance in its features; its
            # confidence a hand-made function of instance size and distance) instead of the learned
            # detector's, so the oracle switch's effect is measured
            Row(
                "tsrm_demae_oracle",
                "TSRM + DE-MAE, oracle switch",
                "demae",
                "tsrm",
                C_TARGET,
                dict(zip(ABLATION_FLAGS, (1, 1, 1))),
                detections="oracle",
            ),
        ]
    if name == "pretraining":
        rows = [Row("resnet18", "Baseline (ResNet18)", "resnet18", "baseline")]
        if vc1:
            rows.append(Row("vc1", "VC-1 (ViT-Base, Ego4D)", "vc1", "baseline"))
        return rows + [
            Row("mae", "Standard MAE (ViT)", "mae", "baseline"),
            Row("demae_crop", "DE-MAE (ViT) w/ crop", "demae-crop", "baseline"),
            Row("demae", "DE-MAE (ViT) w/o crop", "demae", "baseline"),
        ]
    if name == DEMO:
        return [Row("tsrm_demae", "TSRM + DE-MAE", "demae", "tsrm")]
    if name == "threshold":
        return [
            Row(f"c{int(round(100 * c)):02d}", f"C_target = {c:.1f}", "demae", "tsrm", c)
            for c in np.round(np.arange(0.1, 0.91, 0.1), 2).tolist()
        ]
    raise ValueError(f"unknown experiment {name!r} (choose from {', '.join(EXPERIMENTS + (DEMO,))})")


#: Per experiment: evaluation split, metrics in the table, check-mark columns, row shown in the gallery.
EXPERIMENT_INFO = {
    "ablation": dict(
        split="test",
        metrics=list(METRICS),
        flags=list(ABLATION_FLAGS),
        gallery_row="tsrm_demae",
        baseline_row="baseline",
        description="Paper Table II: TSRM terms and DE-MAE added to the baseline.",
    ),
    "pretraining": dict(
        split="test",
        metrics=["SR", "SPL"],
        flags=[],
        gallery_row="demae",
        baseline_row="resnet18",
        description="Paper Table III: pretraining methods of the image encoder, baseline reward.",
    ),
    "threshold": dict(
        split="val",
        metrics=list(METRICS),
        flags=[],
        gallery_row="c70",
        baseline_row="c70",
        description="Paper Fig. 4: the stage-switch threshold C_target swept on validation episodes.",
    ),
    DEMO: dict(
        split="test",
        metrics=list(METRICS),
        flags=[],
        gallery_row="tsrm_demae",
        baseline_row="tsrm_demae",
        description="tsnav demo: TSRM + DE-MAE (paper Table II, last row) at the demo scale.",
    ),
}


@dataclass
class ExperimentConfig:
    """A resolved experiment (saved as ``experiment.json``)."""

    experiment: str
    """``ablation``, ``pretraining``, ``threshold`` or ``demo``."""
    data: str
    """Dataset root (train scenes for pretraining and training, test / val scenes for evaluation)."""
    out: str
    """Experiment folder."""
    scale: str = "small"
    """Name of the :class:`ScaleConfig`."""
    seeds: int = 1
    """Trained agents per row (seeds 0 .. seeds-1); the table reports the mean and 95 % t-interval."""
    minutes_per_job: float | None = None
    """Overrides the scale's training budget per job (minutes)."""
    updates_per_job: int | None = None
    """Overrides the scale's training budget per job with a number of optimizer updates, the same on any
    machine however busy (no minute limit unless ``minutes_per_job`` is also set; the first budget reached
    stops training)."""
    pretrain_dir: str | None = None
    """Where pretraining runs live (default ``OUT/pretrain``); share it between experiments."""
    detections: str = "learned"
    """Detection tables the agents read and the stage switch follows (issue 14 item 4: the learned detector).
    ``oracle`` tables are computed when missing; any other name (``learned``) is used as it is when every scene
    holds one made by the same learned detector, and otherwise the detector in ``detector_dir`` is trained on the
    train rooms (resumable), calibrated on val and its tables written into the scenes that lack one. A row may
    name its own table (:attr:`Row.detections`)."""
    detector_dir: str | None = None
    """Where the learned detector is trained (default ``OUT/detector``); share it between experiments on one
    world."""
    detector: str = "train"
    """Where missing learned tables come from: ``train`` (the detector in ``detector_dir``, trained here) or
    ``shipped`` (:mod:`tsnav.detect.shipped`: the detector that comes with tsnav, trained on the 80 ithor-real
    training rooms at 128x128; the tables of the medium-scale runs in docs/RESULTS.md are its tables)."""
    vc1_weights: str | None = None
    """Published VC-1 ViT-Base weights (timm layout); adds the VC-1 row to the pretraining experiment."""
    resnet18_weights: str | None = None
    """torchvision-layout ResNet18 weights (e.g. ImageNet, like the paper); without them the ResNet18 baseline
    is pretrained here, supervised on the categories visible in the train frames."""
    device: str = "auto"
    """Device of pretraining, features and training (``auto``: CUDA when present)."""
    seed_offset: int = 0
    """Added to the job seeds (repeat an experiment with other seeds)."""
    parallel: int = 1
    """Jobs trained at once, each in its own process (use 2 on two idle cores; progress bars are then off)."""
    procs: int | None = None
    """Overrides the scale's ``ScaleConfig.train.procs``: processes of each batched training job (one job at a time,
    ``parallel`` 1)."""
    checkpoint: str = "best"
    """Checkpoint each job evaluates: ``best`` (issue 15: the job's milestones are scored greedily on validation
    episodes, ``OUT/episodes_select.json``, and the best is kept as ``train/best``) or ``latest`` (the last one
    trained, as experiment folders did before selection existed)."""
    sample: bool = False
    """Evaluate the agents by sampling their actions (seeded) instead of the greedy argmax, the lineage's
    test-time rule."""
    rows: tuple = ()
    """Ids of the rows to run (:attr:`Row.id`); empty: all of the experiment's. Not part of the folder's identity:
    another call with other rows adds them to the same folder, and the tables show the rows of the last call."""
    protocol: str = "paper"
    """Success protocol (:mod:`tsnav.protocol`) of the episode lists, the training runs and the evaluations:
    ``paper`` (in view within 1.0 m) or ``lineage`` (the 1.5 m visibility map, as the lineage's evaluator)."""
    blocked_action: bool = False
    """A deviation from the paper (:attr:`tsnav.agent.AgentConfig.blocked_action`, ``--blocked-action``): every job's
    agent is told when its last MoveAhead left it where it was, as the shipped agent is; named in ``table.md``."""
    select_per_room_type: int | None = None
    """Validation episodes per room type on which each job's milestones are scored (``checkpoint == "best"``);
    None: the scale's ``val_per_room_type`` (100 at the medium scale). The shipped agent was chosen on 500
    (``--select-per-room-type 500``: 2000 episodes of the 20 val rooms). Part of the folder's identity."""
    train_data: str | None = None
    """Dataset root of the training rooms when they are not ``data``'s own (the demo's ``train_world``: some of
    ``data``'s training rooms, linked); None: ``data``."""
    reuse_from: tuple[str, ...] = ()
    """Other experiment folders whose finished jobs may be reused: a job whose training configuration (budget
    included) equals one of theirs copies that trained run instead of training again, then selects its checkpoint
    and is evaluated here as usual (Table III's ResNet18 and DE-MAE rows are Table II's baseline and
    "+ DE-MAE alone" rows). Not part of the folder's identity: it changes no result."""
    threads: int | None = None
    """Torch CPU threads of the experiment's process and of each job (None: ``DEFAULT_THREADS`` of
    :mod:`tsnav.pipeline.experiment`, or the machine's cores when fewer). A fixed count, not the idle cores:
    another count sums floats in another order and trains another agent."""

    #: Allowed values of fields (the command-line options' choices, :mod:`tsnav.settings`).
    CHOICES: ClassVar[dict] = {
        "experiment": (*EXPERIMENTS, DEMO),
        "scale": ("demo", "small", "medium", "paper"),
        "detector": DETECTOR_SOURCES,
        "checkpoint": ("best", "latest"),
        "protocol": PROTOCOLS,
    }
