"""``tsnav experiment ablation|pretraining|threshold``: the paper's experiments as resumable job lists.

    tsnav experiment ablation    --data DIR --out DIR [--scale small|paper] [--seeds N] [--minutes-per-job M]
    tsnav experiment pretraining --data DIR --out DIR [... --vc1-weights PATH]
    tsnav experiment threshold   --data DIR --out DIR [...]

=============  ===========================================================================  ==============
experiment     rows                                                                         paper
=============  ===========================================================================  ==============
ablation       baseline (ResNet18 features, baseline reward); + exploration; + distance;    Table II
               + both (TSRM); + DE-MAE alone (DE-MAE features, baseline reward); all three
               - SR, SPL, SSR, SSSPL, NSNPL for ALL and L>=5, test episodes
pretraining    ResNet18 baseline, (VC-1 with --vc1-weights), standard MAE, DE-MAE w/ crop,  Table III
               DE-MAE w/o crop - all with the baseline reward; SR, SPL for ALL and L>=5
threshold      C_target = 0.1 .. 0.9 (DE-MAE features, TSRM reward), validation episodes;   Fig. 4
               every metric over C_target with its best point marked (threshold.png)
=============  ===========================================================================  ==============

A job is one (row, seed): (pretrain the row's encoder if needed) -> cache its features (once per encoder) ->
train the agent -> evaluate it. The shared stages run once and are reused: pretraining runs live in
``--pretrain-dir`` (default ``OUT/pretrain``), feature caches are ``features_<encoder>-<fingerprint>.hdf5`` in
the scene folders (so identical encoders share them across experiments), detection tables and episode lists
are made once. Every stage resumes after an interruption; a job whose folder holds ``DONE`` is skipped.

Output folder::

    OUT/experiment.json          resolved configuration, rows, jobs (rewritten at every start)
    OUT/episodes_<split>.json    the fixed evaluation episodes
    OUT/jobs/<row>_s<seed>/      train/ (run folder of the trainer), eval/ (records.jsonl, metrics.json,
                                 trajectories.jsonl), DONE (summary, written last)
    OUT/results.json, OUT/table.md, OUT/table.csv
                                 mean and 95 % t-interval over seeds per row, rewritten after every job
    OUT/threshold.png            (threshold) each metric over C_target, best point marked with a red star

Scales: ``small`` fits a 2-core CPU in about two hours on the ``demo`` world (ViT-Tiny at 64x64, short
pretraining, a few minutes of batched training per job); ``paper`` uses the paper's settings (ViT-Base at
224x224, 1.5 M training episodes, A3C with 14 workers) and needs a GPU and days.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..atomic import atomic_write_text
from .metrics import METRICS, summarize, write_json, write_records
from .tables import SUBSETS, aggregate, csv_table, markdown_table, plot_threshold

EXPERIMENTS = ("ablation", "pretraining", "threshold")


# ---------------------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------------------


@dataclass
class ScaleConfig:
    """Sizes of every stage at one scale (``small``: 2-core CPU; ``paper``: the paper's settings)."""

    vit_model: str = "vit_tiny"
    """ViT size of the MAE-family encoders (paper: ViT-Base)."""
    patch_size: int = 16
    """ViT patch side, pixels."""
    img_size: int = 64
    """Encoder input side, pixels (frames are resized to it; paper: 224)."""
    pretrain_steps: int | None = 800
    """Optimiser steps of each pretraining run; None: ``PretrainConfig.epochs`` passes over the data."""
    pretrain_batch_size: int = 64
    """Images per pretraining step."""
    pretrain_base_lr: float | None = 1.5e-3
    """Pretraining learning rate per 256 images of the MAE-family methods; None: MAE's 1.5e-4. Short CPU runs
    use a larger one."""
    resnet_pretrain_steps: int | None = 400
    """Optimiser steps of the supervised ResNet18 baseline (used when no ImageNet weights are given); None: as
    ``pretrain_steps``."""
    feature_batch_size: int = 128
    """Frames per encoder call when caching features."""
    algo: str = "batched"
    """Trainer: ``batched`` (synchronous A2C over many episodes) or ``a3c`` (paper: 14 asynchronous workers)."""
    agent_preset: str = "cpu"
    """Agent network size (:data:`tsnav.agent.PRESETS`; paper: ``paper``)."""
    lr: float = 1e-3
    """Adam learning rate of the agent (paper: 1e-4; short CPU runs need a larger one)."""
    num_envs: int = 64
    """Episodes stepped together by the batched trainer."""
    workers: int = 14
    """A3C workers (paper: 14)."""
    minutes_per_job: float | None = 4.0
    """Training budget per job in minutes (None: ``episodes_per_job``)."""
    episodes_per_job: int | None = None
    """Training budget per job in episodes (paper: 1.5 M)."""
    updates_per_job: int | None = None
    """Training budget per job in optimizer updates (tests). Training stops at the first budget reached; with
    none set, the paper's 1.5 M episodes."""
    test_per_room_type: int = 250
    """Test episodes per room type (the lineage: 250)."""
    val_per_room_type: int = 100
    """Validation episodes per room type (threshold sweep)."""
    max_steps: int = 100
    """Evaluation episode length (paper: 100)."""


SCALES = {
    "small": ScaleConfig(),
    "paper": ScaleConfig(vit_model="vit_base", patch_size=16, img_size=224, pretrain_steps=None, pretrain_batch_size=64,
                         pretrain_base_lr=None, feature_batch_size=64, algo="a3c", agent_preset="paper", lr=1e-4,
                         num_envs=16, workers=14, minutes_per_job=None, episodes_per_job=1_500_000,
                         test_per_room_type=250, val_per_room_type=250),
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
    c_target: float = 0.7
    """Stage-switch threshold for training and evaluation (paper: 0.7)."""
    flags: dict = field(default_factory=dict)
    """Check-mark columns of the table (Table II: exploration reward, distance reward, DE-MAE)."""


ABLATION_FLAGS = ("Exploration Reward", "Distance Reward", "DE-MAE")


def _abl(id_, label, enc, reward, e, d, m) -> Row:
    return Row(id_, label, enc, reward, 0.7, dict(zip(ABLATION_FLAGS, (e, d, m))))


def experiment_rows(name: str, vc1: bool = False) -> list[Row]:
    """The rows of an experiment (paper Table II, Table III, Fig. 4)."""
    if name == "ablation":
        return [_abl("baseline", "baseline (ResNet18, baseline reward)", "resnet18", "baseline", 0, 0, 0),
                _abl("explore", "+ exploration reward", "resnet18", "explore", 1, 0, 0),
                _abl("distance", "+ distance reward", "resnet18", "distance", 0, 1, 0),
                _abl("tsrm", "+ both (TSRM)", "resnet18", "tsrm", 1, 1, 0),
                _abl("demae", "+ DE-MAE alone", "demae", "baseline", 0, 0, 1),
                _abl("tsrm_demae", "TSRM + DE-MAE", "demae", "tsrm", 1, 1, 1)]
    if name == "pretraining":
        rows = [Row("resnet18", "Baseline (ResNet18)", "resnet18", "baseline")]
        if vc1:
            rows.append(Row("vc1", "VC-1 (ViT-Base, Ego4D)", "vc1", "baseline"))
        return rows + [Row("mae", "Standard MAE (ViT)", "mae", "baseline"),
                       Row("demae_crop", "DE-MAE (ViT) w/ crop", "demae-crop", "baseline"),
                       Row("demae", "DE-MAE (ViT) w/o crop", "demae", "baseline")]
    if name == "threshold":
        return [Row(f"c{int(round(100 * c)):02d}", f"C_target = {c:.1f}", "demae", "tsrm", c)
                for c in np.round(np.arange(0.1, 0.91, 0.1), 2).tolist()]
    raise ValueError(f"unknown experiment {name!r} (choose from {', '.join(EXPERIMENTS)})")


#: Per experiment: evaluation split, metrics in the table, check-mark columns, row shown in the gallery.
EXPERIMENT_INFO = {
    "ablation": dict(split="test", metrics=list(METRICS), flags=list(ABLATION_FLAGS), gallery_row="tsrm_demae",
                     description="Paper Table II: TSRM terms and DE-MAE added to the baseline."),
    "pretraining": dict(split="test", metrics=["SR", "SPL"], flags=[], gallery_row="demae",
                        description="Paper Table III: pretraining methods of the image encoder, baseline reward."),
    "threshold": dict(split="val", metrics=list(METRICS), flags=[], gallery_row="c70",
                      description="Paper Fig. 4: the stage-switch threshold C_target swept on validation episodes."),
}


@dataclass
class ExperimentConfig:
    """A resolved experiment (saved as ``experiment.json``)."""

    experiment: str
    """``ablation``, ``pretraining`` or ``threshold``."""
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
    detections: str = "oracle"
    """Detection tables driving the stage switch; ``oracle`` tables are computed when missing, other names
    must exist (``tsnav detect``)."""
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
    sample: bool = False
    """Evaluate the agents by sampling their actions (seeded) instead of the greedy argmax, the lineage's
    test-time rule."""


# ---------------------------------------------------------------------------------------------------------
# Stages shared by jobs: detections, episodes, encoders, features
# ---------------------------------------------------------------------------------------------------------


def busy_cores(samples: int = 5, interval: float = 0.1) -> int:
    """Runnable processes besides this one (median of a few reads of ``/proc/loadavg``); 0 when unknown."""
    counts = []
    for k in range(samples):
        try:
            running = int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
        except (OSError, ValueError, IndexError):
            return 0
        counts.append(max(0, running - 1))
        if k + 1 < samples:
            time.sleep(interval)
    return int(np.median(counts))


def auto_threads() -> int:
    """Torch CPU threads for this machine: the cores not busy with other processes, at least 1. Oversubscribed
    OpenMP threads spin against each other: on a shared 2-core machine one thread can be several times faster
    than two."""
    cores = os.cpu_count() or 1
    return max(1, min(cores, cores - busy_cores()))


def set_threads(n: int | None) -> int:
    """Set torch's CPU threads (None: :func:`auto_threads`); returns the number set."""
    import torch

    n = auto_threads() if n is None else n
    torch.set_num_threads(n)
    return n


def say(msg: str) -> None:
    print(msg, flush=True)


def ensure_oracle_detections(data: str | Path, name: str = "oracle") -> int:
    """Write the oracle detector's table ``detections_<name>.hdf5`` into every scene lacking one made by the same
    oracle configuration; returns the number of scenes written."""
    from ..data.reader import list_scenes, load_scene
    from ..detect.oracle import OracleConfig, oracle_detections
    from ..detect.table import read_fingerprint, write_detections

    cfg = OracleConfig()
    fp = cfg.fingerprint()
    n = 0
    for p in list_scenes(data):
        have = read_fingerprint(p, name)
        if have == fp:
            continue
        if have is not None:
            raise ValueError(f"{p / f'detections_{name}.hdf5'} was made by another detector ({have}); "
                             f"remove it or use another --detections name")
        write_detections(p, name, oracle_detections(load_scene(p), cfg))
        n += 1
    return n


def ensure_detections(data: str | Path, name: str) -> None:
    """Oracle tables are computed when missing; other tables must exist in every scene."""
    from ..data.reader import list_scenes
    from ..detect.table import detections_path

    if name == "oracle":
        n = ensure_oracle_detections(data, name)
        if n:
            say(f"detections: oracle tables written for {n} scenes")
        return
    missing = [p.name for p in list_scenes(data) if not detections_path(p, name).exists()]
    if missing:
        from ..cli import CommandError

        raise CommandError(f"scene {missing[0]} has no detections_{name}.hdf5 (run `tsnav detect --name {name}`)")


def ensure_episodes(data: str | Path, split: str, path: str | Path, per_room_type: int, seed: int = 0,
                    success_distance: float = 1.0) -> Path:
    """The fixed episode list of ``split`` at ``path`` (made once; reused when present)."""
    from ..sim.batch import SceneBank
    from ..sim.episodes import make_episodes, write_episodes

    path = Path(path)
    if path.exists():
        return path
    bank = SceneBank.from_root(data, split, success_distance=success_distance)
    eps = make_episodes(bank, per_room_type, seed)
    if not eps:
        raise ValueError(f"{data}: no valid episode in split {split!r}")
    write_episodes(path, eps, split=split, seed=seed, success_distance=success_distance, per_room_type=per_room_type,
                   start_horizon=0, room_targets=True, data=str(Path(data).resolve()))
    return path


@dataclass
class EncoderSpec:
    """How to obtain an encoder: a ``tsnav features`` spec, the ViT sizes for ``vit:``/``untrained:`` specs, and
    the pretraining run that produces it (None when nothing needs training)."""

    id: str
    spec: str
    model: str = "vit_base"
    patch_size: int = 16
    img_size: int = 224
    pretrain: dict | None = None
    """``PretrainConfig`` fields of the run in ``pretrain_dir/<id>`` (None: use ``spec`` as it is)."""


def encoder_spec(enc: str, scale: ScaleConfig, pretrain_dir: Path, cfg: ExperimentConfig) -> EncoderSpec:
    """The :class:`EncoderSpec` of an encoder id of the rows at a scale."""
    if enc == "vc1":
        if not cfg.vc1_weights:
            raise ValueError("the VC-1 row needs --vc1-weights PATH")
        return EncoderSpec("vc1", f"vit:{cfg.vc1_weights}", "vit_base", 16, 224)
    if enc == "resnet18":
        if cfg.resnet18_weights:
            return EncoderSpec("resnet18", f"resnet18:{cfg.resnet18_weights}", img_size=scale.img_size)
        method = "resnet18-sup"
    elif enc in ("demae", "mae", "demae-crop"):
        method = enc
    else:
        raise ValueError(f"unknown encoder {enc!r}")
    run = pretrain_dir / method
    sup = method == "resnet18-sup"
    steps = scale.resnet_pretrain_steps if sup and scale.resnet_pretrain_steps is not None else scale.pretrain_steps
    pre = dict(method=method, model=scale.vit_model, patch_size=scale.patch_size, img_size=scale.img_size,
               steps=steps, batch_size=scale.pretrain_batch_size, base_lr=None if sup else scale.pretrain_base_lr,
               device=cfg.device)
    return EncoderSpec(enc, str(run), scale.vit_model, scale.patch_size, scale.img_size, pre)


def ensure_encoder(es: EncoderSpec, data: str | Path) -> None:
    """Run (or resume, or skip when finished) the pretraining run of ``es``."""
    if es.pretrain is None:
        return
    from ..pretrain.train import PretrainConfig, train

    say(f"pretrain {es.pretrain['method']} -> {es.spec}")
    res = train(PretrainConfig(**es.pretrain), data, es.spec, progress=True)
    if not res["finished"]:
        raise RuntimeError(f"pretraining {es.spec} did not finish")


def ensure_features(es: EncoderSpec, data: str | Path, splits: list[str], batch_size: int = 128,
                    device: str = "auto") -> str:
    """Cache the features of ``es`` for the scenes of ``splits``; returns the cache name
    ``<id>-<fingerprint>`` (identical encoders share a cache)."""
    from ..pretrain.features import cache_features, load_encoder
    from ..pretrain.train import resolve_device

    enc = load_encoder(es.spec, es.model, es.patch_size, es.img_size, resolve_device(device))
    name = f"{es.id}-{enc.fingerprint[:10]}"
    for s in splits:
        cache_features(enc, data, name, batch_size=batch_size, split=s, progress=True)
    return name


# ---------------------------------------------------------------------------------------------------------
# Evaluation into a folder (also used by the demo)
# ---------------------------------------------------------------------------------------------------------


def evaluate_to_folder(out_dir: str | Path, data: str | Path, episodes_file: str | Path, policy: str = "explorer",
                       run: str | Path | None = None, detections: str | None = None, c_target: float = 0.7,
                       seed: int = 0, label: str | None = None, max_steps: int = 100, sample: bool = False) -> dict:
    """Evaluate a scripted policy (``random`` / ``oracle`` / ``explorer``) or the trained agent of ``run`` on an
    episode list; writes ``records.jsonl``, ``trajectories.jsonl`` and ``metrics.json`` (with everything
    :mod:`tsnav.eval.report` needs to rebuild the bank and the policy). The agent acts greedily (argmax, the
    lineage's test-time rule) unless ``sample``. Returns the :func:`summarize` result."""
    from ..sim.episodes import read_episodes
    from .gallery import record_trajectories, write_trajectories
    from .report import eval_bank, eval_policy
    from .runner import EvalConfig, config_dict

    out_dir = Path(out_dir)
    episodes, emeta = read_episodes(episodes_file)
    config = EvalConfig(max_steps=max_steps, c_target=c_target)
    meta = {"policy": "agent" if run else policy, "run": str(Path(run).resolve()) if run else None, "seed": seed,
            "sample": bool(sample),
            "episodes_file": str(Path(episodes_file).resolve()), "data": str(Path(data).resolve()),
            "success_distance": float(emeta.get("success_distance", 1.0)), "detections": detections,
            "config": config_dict(config), "label": label or (f"agent {Path(run).name}" if run else policy)}
    bank = eval_bank(meta, episodes)
    pol = eval_policy(meta, bank)
    t0 = time.perf_counter()
    records, trajectories = record_trajectories(bank, episodes, pol, config)
    summary = summarize(records, config.min_optimal_length)
    write_records(out_dir / "records.jsonl", records)
    write_trajectories(out_dir / "trajectories.jsonl", trajectories)
    write_json(out_dir / "metrics.json", {**meta, "metrics": summary, "seconds": time.perf_counter() - t0,
                                          "detector_confidence": bank.confidence is not None})
    return summary


# ---------------------------------------------------------------------------------------------------------
# Training (the real trainer of tsnav.rl; tests inject a stand-in)
# ---------------------------------------------------------------------------------------------------------

#: ``train_fn(train_config, agent_config, run_dir)``: trains (or resumes, or skips when finished) a run folder
#: that :func:`tsnav.rl.checkpoint.load_policy` can load.
TrainFn = Callable[[object, object, Path], object]


def default_train_fn() -> TrainFn:
    """The trainer of :mod:`tsnav.rl` (resumable run folders with ``config.json``, checkpoints, ``log.jsonl``)."""
    try:
        from ..rl.train import train_run
    except ImportError as e:
        from ..cli import CommandError

        raise CommandError(f"the agent trainer is not available in this version ({e})") from None
    return train_run


def train_config_for(cfg: ExperimentConfig, scale: ScaleConfig, row: Row, features: str, seed: int):
    """The :class:`~tsnav.rl.config.TrainConfig` and :class:`~tsnav.agent.AgentConfig` of one job."""
    from ..agent import agent_config
    from ..rl.config import TrainConfig

    minutes = cfg.minutes_per_job if cfg.minutes_per_job is not None else scale.minutes_per_job
    episodes, updates = scale.episodes_per_job, scale.updates_per_job
    if cfg.updates_per_job is not None:  # a repeatable budget: no minute limit unless one was asked for too
        updates, minutes = cfg.updates_per_job, cfg.minutes_per_job
    tc = TrainConfig(data=str(Path(cfg.data).resolve()), features=features, detections=cfg.detections,
                     split="train", algo=scale.algo, reward=row.reward, preset=scale.agent_preset, lr=scale.lr,
                     num_envs=scale.num_envs, workers=scale.workers, seed=seed, c_target=row.c_target,
                     minutes=minutes, episodes=episodes, updates=updates, device=cfg.device)
    return tc, agent_config(scale.agent_preset)


# ---------------------------------------------------------------------------------------------------------
# The experiment
# ---------------------------------------------------------------------------------------------------------


@dataclass
class Job:
    row: Row
    seed: int

    @property
    def dir(self) -> str:
        return f"jobs/{self.row.id}_s{self.seed}"


#: experiment.json fields that must match when an experiment folder is resumed.
IDENTITY = ("experiment", "data", "scale", "detections", "resnet18_weights", "vc1_weights", "seed_offset", "sample")
#: Values of IDENTITY fields that folders written before the field existed had (agents were then sampled).
LEGACY_IDENTITY = {"sample": True}


class Experiment:
    """Runs the jobs of one experiment; see the module docstring."""

    def __init__(self, cfg: ExperimentConfig, train_fn: TrainFn | None = None, scale: ScaleConfig | None = None):
        if cfg.experiment not in EXPERIMENTS:
            raise ValueError(f"unknown experiment {cfg.experiment!r} (choose from {', '.join(EXPERIMENTS)})")
        if cfg.scale not in SCALES and scale is None:
            raise ValueError(f"unknown scale {cfg.scale!r} (choose from {', '.join(SCALES)})")
        if cfg.seeds < 1:
            raise ValueError(f"--seeds must be >= 1, got {cfg.seeds}")
        if cfg.parallel < 1:
            raise ValueError(f"--parallel must be >= 1, got {cfg.parallel}")
        if cfg.minutes_per_job is not None and not cfg.minutes_per_job > 0:
            raise ValueError(f"--minutes-per-job must be positive, got {cfg.minutes_per_job}")
        if cfg.updates_per_job is not None and cfg.updates_per_job < 1:
            raise ValueError(f"--updates-per-job must be >= 1, got {cfg.updates_per_job}")
        self.cfg = cfg
        self.scale = scale or SCALES[cfg.scale]
        self.info = EXPERIMENT_INFO[cfg.experiment]
        self.rows = experiment_rows(cfg.experiment, vc1=bool(cfg.vc1_weights))
        self.jobs = [Job(r, cfg.seed_offset + s) for s in range(cfg.seeds) for r in self.rows]
        self.out = Path(cfg.out)
        self.pretrain_dir = Path(cfg.pretrain_dir) if cfg.pretrain_dir else self.out / "pretrain"
        self._train_fn = train_fn

    # -- bookkeeping ----------------------------------------------------------------------------------------
    def _check_and_write_config(self) -> None:
        p = self.out / "experiment.json"
        d = asdict(self.cfg)
        d["data"] = str(Path(self.cfg.data).resolve())
        if p.exists():
            try:
                old = json.loads(p.read_text())
                if not isinstance(old, dict):
                    raise ValueError("not a JSON object")
            except (OSError, ValueError) as e:
                raise ValueError(f"{p}: unreadable experiment file ({e}); use another --out or remove it") from None
            for k in IDENTITY:
                was = old.get("config", {}).get(k, LEGACY_IDENTITY.get(k))
                if was != d.get(k):
                    raise ValueError(f"{self.out} holds the {old.get('experiment')!r} experiment with another {k} "
                                     f"({was!r}, now {d.get(k)!r}); use another --out")
        doc = {"format": "tsnav-experiment", "experiment": self.cfg.experiment, "description": self.info["description"],
               "scale": self.cfg.scale, "seeds": self.cfg.seeds, "config": d, "scale_config": asdict(self.scale),
               "rows": [asdict(r) for r in self.rows], "gallery_row": self.info["gallery_row"],
               "eval_split": self.info["split"],
               "jobs": [{"row": j.row.id, "label": j.row.label, "seed": j.seed, "dir": j.dir} for j in self.jobs]}
        write_json(p, doc)

    def done(self, job: Job) -> bool:
        return (self.out / job.dir / "DONE").exists()

    def write_tables(self) -> dict:
        """Aggregate the finished jobs into ``results.json``, ``table.md``, ``table.csv`` (and ``threshold.png``)."""
        per_row: dict[str, list[dict]] = {}
        for j in self.jobs:
            m = self.out / j.dir / "eval" / "metrics.json"
            if self.done(j) and m.exists():
                per_row.setdefault(j.row.id, []).append(json.loads(m.read_text())["metrics"])
        results = aggregate(self.rows, per_row, self.info["metrics"], self.info["flags"])
        results["experiment"] = self.cfg.experiment
        write_json(self.out / "results.json", results)
        atomic_write_text(self.out / "table.md", f"## {self.cfg.experiment}: {self.info['description']}\n\n"
                           + markdown_table(results)
                           + "\nValues in percent: mean over seeds ± half-width of the 95 % t-interval.\n")
        atomic_write_text(self.out / "table.csv", csv_table(results))
        if self.cfg.experiment == "threshold":
            plot_threshold(results, self.out / "threshold.png")
        return results

    # -- stages ----------------------------------------------------------------------------------------------
    def prepare(self) -> dict[str, str]:
        """Detections, episode list, encoders and feature caches; returns encoder id -> feature name."""
        cfg, scale = self.cfg, self.scale
        split = self.info["split"]
        say(f"[{cfg.experiment}] detections ({cfg.detections}) and {split} episodes")
        ensure_detections(cfg.data, cfg.detections)
        ensure_episodes(cfg.data, split, self.episodes_file,
                        scale.test_per_room_type if split == "test" else scale.val_per_room_type)
        features = {}
        todo = [j for j in self.jobs if not self.done(j)]
        for enc in dict.fromkeys(j.row.encoder for j in todo):
            es = encoder_spec(enc, scale, self.pretrain_dir, cfg)
            ensure_encoder(es, cfg.data)
            say(f"[{cfg.experiment}] features of {enc} for the train and {split} scenes")
            features[enc] = ensure_features(es, cfg.data, ["train", split], scale.feature_batch_size, cfg.device)
        return features

    @property
    def episodes_file(self) -> Path:
        return self.out / f"episodes_{self.info['split']}.json"

    def run_job(self, job: Job, features: str) -> dict:
        """Train (resumable) and evaluate one job; writes ``DONE`` last."""
        jd = self.out / job.dir
        tc, agent = train_config_for(self.cfg, self.scale, job.row, features, job.seed)
        train_fn = self._train_fn or default_train_fn()
        t0 = time.perf_counter()
        train_fn(tc, agent, jd / "train")
        t1 = time.perf_counter()
        summary = evaluate_to_folder(jd / "eval", self.cfg.data, self.episodes_file, run=jd / "train",
                                     detections=self.cfg.detections, c_target=job.row.c_target, seed=job.seed,
                                     label=f"{job.row.label} (seed {job.seed})", max_steps=self.scale.max_steps,
                                     sample=self.cfg.sample)
        done = {"row": job.row.id, "seed": job.seed, "train_seconds": t1 - t0,
                "eval_seconds": time.perf_counter() - t1, "metrics": {s: summary[s] for s in SUBSETS}}
        write_json(jd / "DONE", done)
        return done

    def run(self) -> dict:
        """Run every unfinished job (one after another, or ``cfg.parallel`` at once); returns ``results.json``'s
        content."""
        self.out.mkdir(parents=True, exist_ok=True)
        self._check_and_write_config()
        features = self.prepare()
        todo = [j for j in self.jobs if not self.done(j)]
        skipped = len(self.jobs) - len(todo)
        say(f"[{self.cfg.experiment}] {len(self.jobs)} jobs: {skipped} finished, {len(todo)} to run")
        t_start = time.perf_counter()
        name = self.cfg.experiment

        def report(k: int, job: Job, res: dict) -> None:
            a = res["metrics"]["ALL"]
            say(f"[{name}] job {k}/{len(todo)} ({job.row.label}, seed {job.seed}) done in "
                f"{res['train_seconds'] + res['eval_seconds']:.0f} s: "
                + ", ".join(f"{m} {100 * a[m]:.1f}" for m in METRICS)
                + f" (elapsed {(time.perf_counter() - t_start) / 60:.1f} min)")
            self.write_tables()

        if self.cfg.parallel > 1 and len(todo) > 1 and self._train_fn is None:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            threads = max(1, auto_threads() // self.cfg.parallel)
            with ProcessPoolExecutor(self.cfg.parallel, mp_context=mp.get_context("spawn")) as pool:
                futs = {}
                for job in todo:
                    say(f"[{name}] queued: {job.row.label}, seed {job.seed} -> {self.out / job.dir}")
                    futs[pool.submit(_job_process, self.cfg, self.scale, self.jobs.index(job),
                                     features[job.row.encoder], threads)] = job
                for k, fut in enumerate(as_completed(futs), 1):
                    report(k, futs[fut], fut.result())
        else:
            for k, job in enumerate(todo, 1):
                say(f"[{name}] job {k}/{len(todo)}: {job.row.label}, seed {job.seed} -> {self.out / job.dir}")
                report(k, job, self.run_job(job, features[job.row.encoder]))
        return self.write_tables()


def _job_process(cfg: ExperimentConfig, scale: ScaleConfig, index: int, features: str, threads: int) -> dict:
    """One job in a worker process (``--parallel``): training without a progress bar, then evaluation."""
    from functools import partial

    set_threads(threads)
    exp = Experiment(cfg, train_fn=partial(default_train_fn(), progress_bar=False), scale=scale)
    return exp.run_job(exp.jobs[index], features)


# ---------------------------------------------------------------------------------------------------------
# Command
# ---------------------------------------------------------------------------------------------------------


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("experiment", choices=EXPERIMENTS, help="ablation (Table II), pretraining (Table III), "
                        "threshold (Fig. 4)")
    parser.add_argument("--data", required=True, help="dataset root (train, val and test scenes with images)")
    parser.add_argument("--out", required=True, help="experiment folder (resumed when it exists)")
    parser.add_argument("--scale", choices=sorted(SCALES), default="small",
                        help="small: 2-core CPU, about two hours; paper: the paper's settings (GPU)")
    parser.add_argument("--seeds", type=int, default=1, help="trained agents per row (default 1)")
    parser.add_argument("--minutes-per-job", type=float, default=None,
                        help="training minutes per job (default: the scale's; small: 4)")
    parser.add_argument("--updates-per-job", type=int, default=None,
                        help="training budget per job in optimizer updates instead of minutes: the same on "
                             "a busy machine (small: about 1000 updates in 4 minutes on 2 idle cores)")
    parser.add_argument("--pretrain-dir", default=None, help="pretraining runs (default OUT/pretrain; share it)")
    parser.add_argument("--detections", default="oracle", help="detection tables (default oracle, computed here)")
    parser.add_argument("--vc1-weights", default=None, help="VC-1 ViT-Base weights: adds the VC-1 row (pretraining)")
    parser.add_argument("--resnet18-weights", default=None,
                        help="torchvision ResNet18 weights (ImageNet, as in the paper) for the baseline encoder")
    parser.add_argument("--device", default="auto", help="auto, cpu or cuda")
    parser.add_argument("--parallel", type=int, default=1,
                        help="jobs trained at once, each in its own process (default 1; 2 on two idle cores)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default: the cores not busy with other processes)")
    parser.add_argument("--sample", action="store_true",
                        help="evaluate agents by sampling their actions instead of the greedy argmax (the lineage's "
                             "test-time rule, the default)")
    parser.add_argument("--no-report", action="store_true", help="do not write OUT/report/index.html at the end")


def run(args: argparse.Namespace) -> int:
    from ..cli import CommandError

    if not Path(args.data).is_dir():
        raise CommandError(f"--data {args.data}: no such dataset folder")
    for opt in ("vc1_weights", "resnet18_weights"):
        v = getattr(args, opt)
        if v and not Path(v).exists():
            raise CommandError(f"--{opt.replace('_', '-')} {v}: no such file")
    if args.vc1_weights and args.experiment != "pretraining":
        raise CommandError("--vc1-weights adds a row to the pretraining experiment only")
    cfg = ExperimentConfig(experiment=args.experiment, data=args.data, out=args.out, scale=args.scale, seeds=args.seeds,
                           minutes_per_job=args.minutes_per_job, updates_per_job=args.updates_per_job,
                           pretrain_dir=args.pretrain_dir,
                           detections=args.detections, vc1_weights=args.vc1_weights,
                           resnet18_weights=args.resnet18_weights, device=args.device, parallel=args.parallel,
                           sample=args.sample)
    if args.threads is not None and args.threads < 1:
        raise CommandError("--threads must be >= 1")
    exp = Experiment(cfg)
    say(f"torch threads: {set_threads(args.threads)}")
    results = exp.run()
    print(markdown_table(results))
    print(f"tables: {exp.out / 'table.md'}, {exp.out / 'table.csv'}"
          + (f", plot {exp.out / 'threshold.png'}" if args.experiment == "threshold" else ""))
    if not args.no_report:
        from .report import build_report

        print(f"report: {build_report(exp.out)}")
    return 0
