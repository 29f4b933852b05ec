"""``tsnav experiment ablation|pretraining|threshold``: the paper's experiments as resumable job lists.

    tsnav experiment ablation    --data DIR --out DIR [--scale small|medium|paper] [--seeds N] [--updates-per-job N]
    tsnav experiment pretraining --data DIR --out DIR [... --vc1-weights PATH]
    tsnav experiment threshold   --data DIR --out DIR [...]

=============  ===========================================================================  ==============
experiment     rows                                                                         paper
=============  ===========================================================================  ==============
ablation       baseline (ResNet18 features, baseline reward); + exploration; + distance;    Table II
               + both (TSRM); + DE-MAE alone (DE-MAE features, baseline reward); all three;
               all three with the oracle's table instead of the learned detector's
               ("TSRM + DE-MAE, oracle switch", issue 14)
               - SR, SPL, SSR, SSSPL, NSNPL for ALL and L>=5, test episodes
pretraining    ResNet18 baseline, (VC-1 with --vc1-weights), standard MAE, DE-MAE w/ crop,  Table III
               DE-MAE w/o crop - all with the baseline reward; SR, SPL for ALL and L>=5
threshold      C_target = 0.1 .. 0.9 (DE-MAE features, TSRM reward), validation episodes;   Fig. 4
               every metric over C_target with its best point marked (threshold.png)
=============  ===========================================================================  ==============

Detections (issue 14 item 4): every row's agent reads, and its stage switch follows, the learned detector's table
``detections_learned.hdf5`` (``--detections``; the oracle-switch row of the ablation reads ``detections_oracle``).
When the dataset has learned tables of one detector in every scene they are used as they are; otherwise the
detector is trained on the train rooms in ``--detector-dir`` (default ``OUT/detector``; resumable, sizes and
steps from the scale), calibrated on val, and writes its table into the scenes lacking one (a table of another
detector is never overwritten: one-line error naming it). Each table's quality on the val rooms (presence AP,
reach of C_target, false positives) is written to ``OUT/detector_quality.json`` and printed under the table.

A job is one (row, seed): (pretrain the row's encoder if needed) -> cache its features (once per encoder) ->
train the agent, keeping a milestone every ``ScaleConfig.train.milestone_every`` updates -> score the milestones (and
the newest two checkpoints) greedily on validation episodes and keep the best as ``train/best`` (issue 15;
:func:`tsnav.eval.select.select_checkpoint`, resumed from ``train/selection.json``) -> evaluate that checkpoint.
``--checkpoint latest`` skips selection and evaluates the last checkpoint (as folders from before selection did;
the two kinds are not mixed in one folder). The threshold experiment reports validation episodes too: its
selection episodes are other episodes (another seed) of the same validation rooms, so its table is slightly
optimistic for every row alike. The shared steps run once and are reused: pretraining runs live in
``--pretrain-dir`` (default ``OUT/pretrain``), feature caches are ``features_<encoder>-<fingerprint>.hdf5`` in
the scene folders (so identical encoders share them across experiments), detection tables and episode lists
are made once. Every step resumes after an interruption; a job whose folder holds ``DONE`` is skipped.

Output folder::

    OUT/experiment.json          resolved configuration, rows, jobs (rewritten at every start)
    OUT/detector/                the learned detector's checkpoints (``--detector-dir``), when trained here
    OUT/detector_quality.json    each detection table measured on the val rooms
    OUT/episodes_<split>.json    the fixed evaluation episodes (the experiment's success protocol)
    OUT/episodes_<split>_<p>.json
                                 the same rooms' episodes under the other protocol ``p`` (:mod:`tsnav.protocol`)
    OUT/episodes_select.json     validation episodes that choose each job's checkpoint (``--checkpoint best``)
    OUT/jobs/<row>_s<seed>/      train/ (run folder of the trainer; selection.json, best/), eval/ (records.jsonl,
                                 metrics.json, trajectories.jsonl), DONE (summary with the checkpoint used,
                                 written last), eval_<p>/ (the same checkpoint under the other protocol ``p``,
                                 evaluated once every job is done)
    OUT/results.json, OUT/table.md, OUT/table.csv
                                 mean and 95 % t-interval over seeds per row, rewritten after every job;
                                 table.md has a second table per other protocol (results.json
                                 ``other_protocols``, table_<p>.csv)
    OUT/threshold.png            (threshold) each metric over C_target, best point marked with a red star

Scales: ``demo`` is the scale of ``tsnav demo`` (its one row, TSRM + DE-MAE, in about ten minutes); ``small``
fits a 2-core CPU in about two hours on the ``demo`` world (ViT-Tiny at 64x64, short pretraining, 1000 updates
of batched training per job); ``medium`` is the budget at which the validation curve on the paper's 80 training
rooms plateaus (``ithor-real``, 128 px, 256 episodes per update, 2000 updates per job, measured with
``tsnav convergence``: about 25-35 minutes per job on one core here); ``paper`` uses
the paper's settings (ViT-Base at 224x224, 1.5 M training episodes, A3C with 14 workers) on the ``ithor-real`` world (the 120 real iTHOR scenes) and needs a GPU and days.
``--build-world`` builds the scale's world into a ``--data`` folder that does not exist yet.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Callable

from ..agent import agent_config
from ..atomic import atomic_write_text
from ..distributed import set_threads as distributed_set_threads
from ..distributed import spawn_context
from ..errors import CommandError
from ..settings import add_options, add_shared, apply_sets, dump_recipe, given, merge, read_recipe
from ..rl.checkpoint import resolve_checkpoint
from ..rl.config import TrainConfig
from ..rl.train import train_run
from .config import (
    DETECTOR_SOURCES,
    EXPERIMENTS,
    EXPERIMENT_INFO,
    SCALES,
    ExperimentConfig,
    Row,
    ScaleConfig,
    experiment_rows,
)
from ..metrics import METRICS, write_json
from ..protocol import PROTOCOLS, check_protocol, protocol_line
from ..report.html import build_report
from ..eval.runner import evaluate_to_folder
from ..eval.select import chosen, select_checkpoint
from .detector_steps import QUALITY_FILE, record_quality
from .recipes import SECTIONS as RECIPE_SECTIONS
from .recipes import experiment_recipe, resolve_experiment, same_scale, write_recipe
from .steps import (
    EncoderSpec,
    encoder_spec,
    ensure_detections,
    ensure_encoder,
    ensure_episodes,
    ensure_features,
    ensure_world,
    say,
)
from ..rl.done_dips import DIP_DONE_SHARE, run_done_dips
from ..report.claims import ALPHA as CLAIMS_ALPHA, check_claims, claims_markdown, summary_line
from ..report.tables import (
    SUBSETS,
    aggregate,
    csv_table,
    markdown_table,
    plot_threshold,
    quality_line,
    welch_against,
    welch_markdown,
)


# ---------------------------------------------------------------------------------------------------------
# Threads
# ---------------------------------------------------------------------------------------------------------


#: Torch CPU threads unless ``--threads`` says otherwise. A fixed count, not the cores that happen to be idle:
#: another count sums floats in another order, so the pretrained encoder and the agents (and every table) would
#: depend on how busy the machine was at the start (seen: 2 and 1 threads gave demo agent SR 52.0 and 55.0).
DEFAULT_THREADS = 2


def default_threads() -> int:
    """:data:`DEFAULT_THREADS`, or the machine's cores when it has fewer."""
    return max(1, min(DEFAULT_THREADS, os.cpu_count() or 1))


def set_threads(n: int | None) -> int:
    """Set torch's CPU threads (None: :func:`default_threads`); returns the number set."""
    return distributed_set_threads(default_threads() if n is None else n)


# ---------------------------------------------------------------------------------------------------------
# Training (the real trainer of tsnav.rl; tests inject a stand-in)
# ---------------------------------------------------------------------------------------------------------

#: ``train_fn(train_config, agent_config, run_dir)``: trains (or resumes, or skips when finished) a run folder
#: that :func:`tsnav.rl.checkpoint.load_policy` can load.
TrainFn = Callable[[object, object, Path], object]


def default_train_fn() -> TrainFn:
    """The trainer of :mod:`tsnav.rl` (resumable run folders with ``config.json``, checkpoints, ``log.jsonl``)."""
    return train_run


def train_config_for(cfg: ExperimentConfig, scale: ScaleConfig, row: Row, features: str, seed: int):
    """The :class:`~tsnav.rl.config.TrainConfig` and :class:`~tsnav.agent.AgentConfig` of one job."""
    base = scale.train
    budget = {}
    if cfg.updates_per_job is not None or cfg.minutes_per_job is not None:  # asked for: replaces the scale's
        budget = dict(episodes=None, updates=cfg.updates_per_job, minutes=cfg.minutes_per_job)
    milestones = base.milestone_every if cfg.checkpoint == "best" else None
    # checkpoints land on multiples of checkpoint_every (100 by default); milestones must be among them
    every = math.gcd(TrainConfig.checkpoint_every, milestones) if milestones else TrainConfig.checkpoint_every
    tc = replace(
        base,
        data=str(Path(cfg.train_data or cfg.data).resolve()),
        features=features,
        detections=row.detections_of(cfg.detections),
        split="train",
        reward=row.reward,
        seed=seed,
        c_target=row.c_target,
        device=cfg.device,
        checkpoint_every=every,
        milestone_every=milestones,
        protocol=cfg.protocol,
        procs=(cfg.procs or base.procs) if base.algo == "batched" else 1,
        **budget,
    )
    return tc, agent_config(base.preset, **{**scale.agent, **({"blocked_action": True} if cfg.blocked_action else {})})


# ---------------------------------------------------------------------------------------------------------
# The job list: steps whose DONE file (written last, atomically) marks them finished
# ---------------------------------------------------------------------------------------------------------

#: The marker of a finished step or job: ``<folder>/DONE``, a JSON summary written last and atomically.
DONE = "DONE"


def read_done(folder: str | Path, legacy: str | Path | None = None) -> dict | None:
    """The summary in ``folder/DONE`` (else in the ``legacy`` marker file, when given), or None when there is none
    or it is unreadable."""
    for p in (Path(folder) / DONE, legacy):
        if p is not None and Path(p).exists():
            try:
                m = json.loads(Path(p).read_text())
            except (OSError, ValueError):
                return None
            return m if isinstance(m, dict) else None
    return None


def write_done(folder: str | Path, summary: dict) -> dict:
    """Mark a step finished: ``folder/DONE`` holds ``summary`` (atomic; call it after the step's outputs)."""
    Path(folder).mkdir(parents=True, exist_ok=True)
    write_json(Path(folder) / DONE, summary)
    return summary


@dataclass
class Step:
    """One entry of a :class:`JobList`: ``run() -> summary`` (None: the step does not apply and is shown as
    ``-``), its ``DONE`` in ``folder``, ``valid(marker)`` whether a finished step's outputs are still there,
    ``show(marker)`` what is printed after it ran or was reused."""

    name: str
    what: str
    folder: Path
    run: Callable[[], dict] | None
    valid: Callable[[dict], bool] = lambda m: True
    show: Callable[[dict], None] | None = None
    legacy: Path | None = None
    """A marker file of an earlier layout, read when ``DONE`` is missing (the demo's ``stages/<name>.json``)."""
    writes_done: bool = False
    """``run`` writes the step's ``DONE`` itself (an experiment's job, whose marker is its result) and returns
    that marker; the job list then keeps it as it is."""


class JobList:
    """Runs steps in order, numbered ``[k/n]``. A step is reused when its marker is valid and no earlier step ran
    in this call (``chained``: each step reads what the ones before wrote; the underlying work skips what is on
    disk, so a rerun after an upstream change is cheap), else it runs and its ``DONE`` is written (with its
    seconds). ``times``: name -> (``done`` / ``reused`` / ``-``, seconds); ``markers``: name -> summary."""

    def __init__(self, steps: list[Step], chained: bool = True, say: Callable[[str], None] = say):
        self.steps, self.chained, self.say = steps, chained, say
        self.times: dict[str, tuple[str, float]] = {}
        self.markers: dict[str, dict] = {}

    def run_step(self, k: int, step: Step) -> dict:
        self.say(f"\n[{k}/{len(self.steps)}] {step.name}: {step.what}")
        if step.run is None:
            self.times[step.name] = ("-", 0.0)
            return {}
        m = read_done(step.folder, step.legacy)
        upstream_ran = self.chained and any(status == "done" for status, _ in self.times.values())
        if m is not None and not upstream_ran and step.valid(m):
            self.say(f"    reused (made by an earlier run in {m.get('seconds', 0):.0f} s)")
            self.times[step.name] = ("reused", 0.0)
        else:
            t0 = time.perf_counter()
            summary = step.run() or {}
            dt = time.perf_counter() - t0
            m = summary if step.writes_done else write_done(step.folder, {**summary, "seconds": dt})
            self.times[step.name] = ("done", dt)
            self.say(f"    done in {dt:.0f} s")
        self.markers[step.name] = m
        if step.show is not None:
            step.show(m)
        return m

    def run(self) -> dict[str, dict]:
        for k, step in enumerate(self.steps, 1):
            self.run_step(k, step)
        return self.markers


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
IDENTITY = (
    "experiment",
    "data",
    "scale",
    "detections",
    "resnet18_weights",
    "vc1_weights",
    "seed_offset",
    "sample",
    "checkpoint",
    "protocol",
    "blocked_action",
    "select_per_room_type",
)
#: Values of IDENTITY fields that folders written before the field existed had (agents were then sampled, and
#: the latest checkpoint was evaluated).
LEGACY_IDENTITY = {
    "sample": True,
    "checkpoint": "latest",
    "protocol": "paper",
    "blocked_action": False,
    "select_per_room_type": None,
}
#: ``ExperimentConfig.checkpoint`` values.
CHECKPOINTS = ("best", "latest")
#: Seed of the selection episodes (the threshold experiment's evaluation episodes on val use seed 0).
SELECT_SEED = 1


class Experiment:
    """Runs the jobs of one experiment; see the module docstring."""

    writes_recipe = True
    """Write the resolved recipe ``OUT/recipe.toml`` beside ``experiment.json`` (the demo writes its own)."""

    def __init__(self, cfg: ExperimentConfig, train_fn: TrainFn | None = None, scale: ScaleConfig | None = None):
        if cfg.experiment not in EXPERIMENT_INFO:
            raise ValueError(f"unknown experiment {cfg.experiment!r} (choose from {', '.join(EXPERIMENT_INFO)})")
        if cfg.scale not in SCALES and scale is None:
            raise ValueError(f"unknown scale {cfg.scale!r} (choose from {', '.join(SCALES)})")
        if cfg.seeds < 1:
            raise ValueError(f"--seeds must be >= 1, got {cfg.seeds}")
        if cfg.parallel < 1:
            raise ValueError(f"--parallel must be >= 1, got {cfg.parallel}")
        if cfg.procs is not None and (cfg.procs < 1 or (cfg.procs > 1 and cfg.parallel > 1)):
            raise ValueError(f"--procs must be >= 1, and 1 with --parallel > 1 (got --procs {cfg.procs})")
        if cfg.minutes_per_job is not None and not cfg.minutes_per_job > 0:
            raise ValueError(f"--minutes-per-job must be positive, got {cfg.minutes_per_job}")
        if cfg.updates_per_job is not None and cfg.updates_per_job < 1:
            raise ValueError(f"--updates-per-job must be >= 1, got {cfg.updates_per_job}")
        if cfg.select_per_room_type is not None:
            if (
                isinstance(cfg.select_per_room_type, bool)
                or not isinstance(cfg.select_per_room_type, int)
                or cfg.select_per_room_type < 1
            ):
                raise ValueError(f"--select-per-room-type must be an integer >= 1, got {cfg.select_per_room_type!r}")
            if cfg.checkpoint != "best":
                raise ValueError(
                    "--select-per-room-type needs --checkpoint best (with latest no checkpoint is selected)"
                )
        if cfg.detector not in DETECTOR_SOURCES:
            raise ValueError(f"--detector must be train or shipped, got {cfg.detector!r}")
        if cfg.checkpoint not in CHECKPOINTS:
            raise ValueError(f"--checkpoint must be one of {', '.join(CHECKPOINTS)}, got {cfg.checkpoint!r}")
        self.scale = scale or SCALES[cfg.scale]
        if cfg.select_per_room_type == self.scale.val_per_room_type:  # the scale's own count: the same folder
            cfg = replace(cfg, select_per_room_type=None)
        self.cfg = cfg
        self.info = EXPERIMENT_INFO[cfg.experiment]
        self.rows = experiment_rows(cfg.experiment, vc1=bool(cfg.vc1_weights))
        if cfg.rows:
            ids = [r.id for r in self.rows]
            unknown = [r for r in cfg.rows if r not in ids]
            if unknown:
                raise ValueError(
                    f"--rows: no row {', '.join(map(repr, unknown))} in the {cfg.experiment} experiment "
                    f"(its rows: {', '.join(ids)})"
                )
            self.rows = [r for r in self.rows if r.id in cfg.rows]
        self.jobs = [Job(r, cfg.seed_offset + s) for s in range(cfg.seeds) for r in self.rows]
        self.out = Path(cfg.out)
        self.pretrain_dir = Path(cfg.pretrain_dir) if cfg.pretrain_dir else self.out / "pretrain"
        self.detector_dir = Path(cfg.detector_dir) if cfg.detector_dir else self.out / "detector"
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
                    raise ValueError(
                        f"{self.out} holds the {old.get('experiment')!r} experiment with another {k} "
                        f"({was!r}, now {d.get(k)!r}); use another --out"
                    )
        doc = {
            "format": "tsnav-experiment",
            "experiment": self.cfg.experiment,
            "description": self.info["description"],
            "scale": self.cfg.scale,
            "seeds": self.cfg.seeds,
            "config": d,
            "scale_config": asdict(self.scale),
            "rows": [asdict(r) for r in self.rows],
            "gallery_row": self.info["gallery_row"],
            "eval_split": self.info["split"],
            "jobs": [{"row": j.row.id, "label": j.row.label, "seed": j.seed, "dir": j.dir} for j in self.jobs],
        }
        write_json(p, doc)
        if self.writes_recipe:
            write_recipe(
                self.out, replace(self.cfg, data=d["data"]), self.scale, f"tsnav experiment {self.cfg.experiment}"
            )

    def done(self, job: Job) -> bool:
        return read_done(self.out / job.dir) is not None

    @property
    def train_root(self) -> Path:
        """Dataset root of the training rooms (pretraining, features, detector and agent training)."""
        return Path(self.cfg.train_data or self.cfg.data)

    def train_dir(self, job: Job) -> Path:
        """The job's run folder."""
        return self.out / job.dir / "train"

    def eval_dir(self, job: Job, protocol: str | None = None) -> Path:
        """The job's evaluation folder under ``protocol`` (default: the experiment's own, ``eval``; another
        protocol's is ``eval_<protocol>``)."""
        if protocol is None or protocol == self.cfg.protocol:
            return self.out / job.dir / "eval"
        return self.out / job.dir / f"eval_{protocol}"

    @property
    def other_protocols(self) -> list[str]:
        """The success protocols the jobs are evaluated under besides the one they are trained under."""
        return [p for p in PROTOCOLS if p != self.cfg.protocol]

    def aggregate_protocol(self, protocol: str | None = None) -> dict:
        """The finished jobs' evaluations under ``protocol`` (default the experiment's), aggregated per row
        (:func:`~tsnav.report.tables.aggregate`); jobs not yet evaluated under it are left out."""
        per_row: dict[str, list[dict]] = {}
        for j in self.jobs:
            m = self.eval_dir(j, protocol) / "metrics.json"
            if self.done(j) and m.exists():
                per_row.setdefault(j.row.id, []).append(json.loads(m.read_text())["metrics"])
        return aggregate(self.rows, per_row, self.info["metrics"], self.info["flags"])

    def other_protocol_results(self, protocol: str, results: dict) -> dict | None:
        """The finished jobs under ``protocol`` (not the experiment's own) aggregated as ``results.json`` holds them
        in ``other_protocols``, with the rows that have fewer seeds than in ``results`` (the experiment's own table)
        as ``incomplete_rows``; None before any job is evaluated there."""
        res = self.aggregate_protocol(protocol)
        if not any(r["n"] for r in res["rows"]):
            return None
        res.update(
            experiment=self.cfg.experiment,
            detections=self.cfg.detections,
            protocol=protocol,
            trained_protocol=self.cfg.protocol,
            welch=welch_against(res, self.info["baseline_row"]),
        )
        short = [r["label"] for r, m in zip(res["rows"], results["rows"]) if r["n"] < m["n"]]
        if short:
            res["incomplete_rows"] = short
        return res

    def write_tables(self) -> dict:
        """Aggregate the finished jobs into ``results.json``, ``table.md``, ``table.csv`` (and ``threshold.png``),
        with a table per other success protocol (``table_<p>.csv``, ``results.json`` ``other_protocols``)."""
        results = self.aggregate_protocol()
        results["experiment"] = self.cfg.experiment
        results["detections"] = self.cfg.detections
        results["protocol"] = self.cfg.protocol
        results["blocked_action"] = self.cfg.blocked_action
        if self.cfg.checkpoint == "best":
            results["select_per_room_type"] = self.select_per_room_type
        results["welch"] = welch_against(results, self.info["baseline_row"])
        quality = self.quality()
        if quality:
            results["detector_quality"] = quality
        dips = self.done_dips()
        results["done_dips"] = dips
        text = (
            f"## {self.cfg.experiment}: {self.info['description']}\n\n"
            + f"Success {protocol_line(self.cfg.protocol, self.cfg.protocol)}.\n\n"
            + markdown_table(results)
            + (
                "\nEvery agent is told when its last MoveAhead failed (`--blocked-action`, a deviation from the "
                "paper).\n"
                if self.cfg.blocked_action
                else ""
            )
            + (
                f"\nEach job's checkpoint is chosen on {self.select_per_room_type} validation episodes per room type "
                "(`--select-per-room-type`).\n"
                if self.cfg.select_per_room_type is not None
                else ""
            )
            + "\nValues in percent: mean over seeds ± half-width of the 95 % t-interval. "
            + f"Detections: {self.cfg.detections}"
            + "".join(f"; row '{r.label}': {r.detections}" for r in self.rows if r.detections)
            + ".\n"
            + "".join(f"\n- {quality_line(q)}" for q in quality.values())
            + ("\n" if quality else "")
        )
        if results["welch"]:
            text += welch_text(
                results,
                f"Differences against '{results['welch']['baseline']}' in percentage points, "
                "Welch's t-test p-value over the per-seed values",
            )
        if dips["jobs"]:
            text += "\n" + dips_line(dips) + "\n"
        text += claims_text(
            self.cfg.experiment, results, f"Against the paper's claims (`tsnav claims`; verdicts at p < {CLAIMS_ALPHA})"
        )
        others = {}
        for p in self.other_protocols:
            res = self.other_protocol_results(p, results)
            if res is None:
                (self.out / f"table_{p}.csv").unlink(missing_ok=True)  # not one job evaluated there (yet)
                continue
            others[p] = res
            text += (
                f"\n### The same agents under the `{p}` protocol\n\nSuccess {protocol_line(p, self.cfg.protocol)}"
                f"; the checkpoints chosen under {self.cfg.protocol}.\n\n" + markdown_table(res)
            )
            if res.get("incomplete_rows"):
                text += (
                    f"\nNot every finished job is evaluated under `{p}` yet (fewer seeds than above): "
                    + ", ".join(res["incomplete_rows"])
                    + ".\n"
                )
            if res["welch"]:
                text += welch_text(res, f"Differences against '{res['welch']['baseline']}' under `{p}`")
            text += claims_text(
                self.cfg.experiment, res, f"Against the paper's claims under `{p}` (`tsnav claims --protocol {p}`)"
            )
            atomic_write_text(self.out / f"table_{p}.csv", csv_table(res))
        if others:
            results["other_protocols"] = others
        atomic_write_text(self.out / "table.md", text)
        atomic_write_text(self.out / "table.csv", csv_table(results))
        write_json(self.out / "results.json", results)
        if self.cfg.experiment == "threshold":
            plot_threshold(results, self.out / "threshold.png")
        return results

    def reusable_run(self, tc: TrainConfig, agent=None) -> Path | None:
        """A finished job's ``train`` folder in one of ``cfg.reuse_from`` whose training configuration equals
        ``tc`` (budget included) and, when given, whose agent configuration equals ``agent``, or None."""
        want = json.loads(json.dumps(tc.to_dict()))  # as config.json holds it (tuples become lists)
        want_agent = None if agent is None else json.loads(json.dumps(asdict(agent)))
        for other in self.cfg.reuse_from:
            root = Path(other)
            if not (root / "experiment.json").exists():
                raise ValueError(f"--reuse-from {other}: not an experiment folder (no experiment.json)")
            for cfg_file in sorted(root.glob("jobs/*/train/config.json")):
                job_dir = cfg_file.parent.parent
                if not (job_dir / "DONE").exists():
                    continue
                try:  # through the config classes, so that fields added since (at their defaults) compare equal
                    stored = json.loads(cfg_file.read_text())
                    have = json.loads(json.dumps(TrainConfig.from_dict(stored["train"]).to_dict()))
                    have_agent = json.loads(json.dumps(asdict(type(agent)(**stored["agent"])))) if agent else None
                except (ValueError, KeyError, TypeError):
                    continue
                if have == want and have_agent == want_agent:
                    return cfg_file.parent
        return None

    def done_dips(self) -> dict:
        """Done dips (:mod:`tsnav.rl.done_dips`) in the training logs of the finished jobs: ``{"jobs": n,
        "with_dips": [{"row", "seed", "dips"}]}``."""
        out = {"jobs": 0, "with_dips": []}
        for j in self.jobs:
            if self.done(j):
                out["jobs"] += 1
                d = run_done_dips(self.train_dir(j))
                if d:
                    out["with_dips"].append({"row": j.row.id, "seed": j.seed, "dips": d})
        return out

    def quality(self) -> dict:
        """``OUT/detector_quality.json`` (the tables measured on val rooms), or {} before it is written."""
        p = self.out / QUALITY_FILE
        try:
            return json.loads(p.read_text()) if p.exists() else {}
        except ValueError:
            return {}

    # -- steps -----------------------------------------------------------------------------------------------
    def prepare(self) -> dict[str, str]:
        """Detections, episode list, encoders and feature caches; returns encoder id -> feature name."""
        cfg, scale = self.cfg, self.scale
        split = self.info["split"]
        ensure_world(cfg.data, scale.world)
        say(f"[{cfg.experiment}] detections ({', '.join(self.detection_names)}) and {split} episodes")
        for name in self.detection_names:
            self.ensure_detections(name)
        record_quality(self.out, cfg.data, self.detection_names, say=say)
        per_type = scale.test_per_room_type if split == "test" else scale.val_per_room_type
        ensure_episodes(cfg.data, split, self.episodes_file, per_type, protocol=cfg.protocol)
        for p in self.other_protocols:
            ensure_episodes(cfg.data, split, self.episodes_file_of(p), per_type, protocol=p)
        splits = ["train", split]
        if cfg.checkpoint == "best":
            say(f"[{cfg.experiment}] validation episodes for checkpoint selection")
            ensure_episodes(
                cfg.data, "val", self.select_file, self.select_per_room_type, seed=SELECT_SEED, protocol=cfg.protocol
            )
            splits = list(dict.fromkeys([*splits, "val"]))
        features = {}
        todo = [j for j in self.jobs if not self.done(j)]
        for enc in dict.fromkeys(j.row.encoder for j in todo):
            es = self.encoder(enc)
            say(f"[{cfg.experiment}] features of {enc} for the {' and '.join(splits)} scenes")
            features[enc] = self.features(es, splits)
        return features

    def ensure_detections(self, name: str) -> dict:
        """The table ``name`` in every scene (:func:`~tsnav.pipeline.steps.ensure_detections`: the one rule on
        tables of another source, the detector trained on the training rooms when needed)."""
        return ensure_detections(
            self.cfg.data,
            name,
            self.detector_dir,
            self.scale,
            shipped=self.cfg.detector == "shipped",
            train_root=self.train_root,
        )

    def encoder(self, enc: str) -> EncoderSpec:
        """The encoder ``enc`` of the rows, pretrained on the training rooms (resumed; nothing when finished)."""
        es = encoder_spec(enc, self.scale, self.pretrain_dir, self.cfg)
        ensure_encoder(es, self.train_root)
        return es

    def features(self, es: EncoderSpec, splits: list[str]) -> str:
        """Cache the features of ``es`` for the scenes of ``splits`` (the train split from the training rooms);
        returns the cache name."""
        bs, device = self.scale.feature_batch_size, self.cfg.device
        if self.cfg.train_data and "train" in splits:
            name = ensure_features(es, self.train_root, ["train"], bs, device)
            rest = [s for s in splits if s != "train"]
            return ensure_features(es, self.cfg.data, rest, bs, device) if rest else name
        return ensure_features(es, self.cfg.data, splits, bs, device)

    @property
    def detection_names(self) -> list[str]:
        """Detection tables the rows read: the experiment's, then rows' own (the oracle-switch row)."""
        return list(dict.fromkeys([self.cfg.detections] + [r.detections_of(self.cfg.detections) for r in self.rows]))

    @property
    def episodes_file(self) -> Path:
        return self.out / f"episodes_{self.info['split']}.json"

    def episodes_file_of(self, protocol: str) -> Path:
        """The evaluation episodes under ``protocol``: the experiment's own file, or ``episodes_<split>_<p>.json``
        (the same rooms, count and seed, drawn under the other protocol's rule)."""
        if protocol == self.cfg.protocol:
            return self.episodes_file
        return self.out / f"episodes_{self.info['split']}_{protocol}.json"

    @property
    def select_per_room_type(self) -> int:
        """Validation episodes per room type of :attr:`select_file` (``--select-per-room-type``, else the scale's)."""
        n = self.cfg.select_per_room_type
        return self.scale.val_per_room_type if n is None else n

    @property
    def select_file(self) -> Path:
        """Validation episodes on which each job's checkpoints are scored (``checkpoint == "best"``)."""
        return self.out / "episodes_select.json"

    def choose_checkpoint(self, job: Job) -> dict:
        """Select the job's checkpoint (``best``: :func:`~tsnav.eval.select.select_checkpoint` on the selection
        episodes, resumed from ``train/selection.json``; ``latest``: the last trained); returns what was used
        (checkpoint name, update, and for ``best`` the validation SR / SPL)."""
        run = self.train_dir(job)
        if self.cfg.checkpoint == "best":
            say(f"[{self.cfg.experiment}] selecting {job.row.id}_s{job.seed}'s checkpoint on {self.select_file.name}")
            sel = select_checkpoint(
                run,
                self.cfg.data,
                self.select_file,
                seed=job.seed,
                max_steps=self.scale.max_steps,
                c_target=job.row.c_target,
                progress=say,
            )
            return {"kind": "best", **chosen(sel)}
        ck = resolve_checkpoint(run, "latest")
        return {
            "kind": "latest",
            "name": ck.name,
            "update": int(json.loads((ck / "state.json").read_text())["progress"]["update"]),
        }

    def train_job(self, job: Job, features: str) -> TrainConfig:
        """Train the job's agent (resumable; a finished run of ``reuse_from`` with this very configuration is
        copied instead); returns its training configuration."""
        tc, agent = train_config_for(self.cfg, self.scale, job.row, features, job.seed)
        run = self.train_dir(job)
        src = None if run.exists() else self.reusable_run(tc, agent)
        if src is not None:  # finished there with this very configuration and budget: nothing to train
            say(f"[{self.cfg.experiment}] {job.row.id}_s{job.seed}: reusing the trained run {src}")
            copy_run(src, run)
        else:
            (self._train_fn or default_train_fn())(tc, agent, run)
        return tc

    def run_job(self, job: Job, features: str) -> dict:
        """Train (resumable) and evaluate one job; writes ``DONE`` last. Evaluations of an earlier run of the job
        under the other protocols are removed first (:meth:`evaluate_other_protocols` makes them again)."""
        for p in self.other_protocols:
            shutil.rmtree(self.eval_dir(job, p), ignore_errors=True)
        t0 = time.perf_counter()
        self.train_job(job, features)
        checkpoint = self.choose_checkpoint(job)
        t1 = time.perf_counter()
        summary = self.evaluate(job, checkpoint["kind"])
        return write_done(
            self.out / job.dir,
            {
                "row": job.row.id,
                "seed": job.seed,
                "checkpoint": checkpoint,
                "train_seconds": t1 - t0,
                "eval_seconds": time.perf_counter() - t1,
                "metrics": {s: summary[s] for s in SUBSETS},
            },
        )

    def evaluate(self, job: Job, checkpoint: str, protocol: str | None = None) -> dict:
        """Evaluate the job's chosen checkpoint (``best`` / ``latest``) on the evaluation episodes of ``protocol``
        (default the experiment's) into :meth:`eval_dir`; returns the summary."""
        p = protocol or self.cfg.protocol
        return evaluate_to_folder(
            self.eval_dir(job, p),
            self.cfg.data,
            self.episodes_file_of(p),
            run=self.train_dir(job),
            detections=job.row.detections_of(self.cfg.detections),
            c_target=job.row.c_target,
            seed=job.seed,
            label=f"{job.row.label} (seed {job.seed})" + ("" if p == self.cfg.protocol else f" [{p}]"),
            max_steps=self.scale.max_steps,
            sample=self.cfg.sample,
            checkpoint=checkpoint,
            protocol=None if p == self.cfg.protocol else p,
        )

    def evaluate_other_protocols(self) -> int:
        """Evaluate every finished job's checkpoint under the other protocols where that is not done yet (one
        after another; each loads the job's rooms again, seconds to a minute); returns how many evaluations ran.
        A job that cannot be evaluated (e.g. a folder from an older tsnav whose run no longer loads) is named in
        one line and left out of the second table; the main table is written either way."""
        ran = 0
        for job in self.jobs:
            done = read_done(self.out / job.dir)
            if done is None:
                continue
            for p in self.other_protocols:
                if (self.eval_dir(job, p) / "metrics.json").exists():
                    continue
                say(f"[{self.cfg.experiment}] {job.row.id}_s{job.seed} under the {p} protocol")
                try:
                    self.evaluate(job, done.get("checkpoint", {}).get("kind", self.cfg.checkpoint), p)
                except (CommandError, ValueError, OSError, KeyError) as e:
                    say(f"[{self.cfg.experiment}] {job.row.id}_s{job.seed} not evaluated under {p}: {e}")
                    continue
                ran += 1
        return ran

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
            say(
                f"[{name}] job {k}/{len(todo)} ({job.row.label}, seed {job.seed}) done in "
                f"{res['train_seconds'] + res['eval_seconds']:.0f} s: "
                + ", ".join(f"{m} {100 * a[m]:.1f}" for m in METRICS)
                + f" (elapsed {(time.perf_counter() - t_start) / 60:.1f} min)"
            )
            self.write_tables()

        if self.cfg.parallel > 1 and len(todo) > 1 and self._train_fn is None:
            threads = max(1, default_threads() // self.cfg.parallel)
            with ProcessPoolExecutor(self.cfg.parallel, mp_context=spawn_context()) as pool:
                futs = {}
                for job in todo:
                    say(f"[{name}] queued: {job.row.label}, seed {job.seed} -> {self.out / job.dir}")
                    futs[
                        pool.submit(
                            _job_process, self.cfg, self.scale, self.jobs.index(job), features[job.row.encoder], threads
                        )
                    ] = job
                for k, fut in enumerate(as_completed(futs), 1):
                    report(k, futs[fut], fut.result())
        else:  # one job list: the jobs still to run, each marked by the DONE its run writes
            steps = [
                Step(
                    f"{name} job {job.row.id}_s{job.seed}",
                    f"{job.row.label}, seed {job.seed} -> {self.out / job.dir}",
                    self.out / job.dir,
                    partial(self.run_job, job, features[job.row.encoder]),
                    show=partial(report, k, job),
                    writes_done=True,
                )
                for k, job in enumerate(todo, 1)
            ]
            JobList(steps, chained=False).run()
        if self.evaluate_other_protocols():
            say(f"[{self.cfg.experiment}] evaluated under {', '.join(self.other_protocols)} as well")
        return self.write_tables()


def welch_text(results: dict, intro: str) -> str:
    """``table.md``'s differences from the baseline row (ALL and L>=5) under a heading line ``intro``."""
    return f"\n{intro}:\n\n" + welch_markdown(results) + "\n" + welch_markdown(results, "L>=5")


def claims_text(experiment: str, results: dict, intro: str) -> str:
    """``table.md``'s check of the paper's claims on ``results`` under a heading line ``intro`` ('' when no claim
    concerns the experiment)."""
    checks = check_claims({experiment: results})
    if not checks:
        return ""
    return f"\n{intro}:\n\n" + claims_markdown(checks) + f"\n{summary_line(checks)}\n"


def copy_run(src: Path, dst: Path) -> None:
    """Copy a trained run folder without its checkpoint selection (``selection.json``, ``best``: the selection
    is redone on this experiment's validation episodes); atomic (a temporary folder renamed into place)."""
    tmp = dst.with_name(dst.name + ".copying")
    if tmp.exists():
        shutil.rmtree(tmp)
    shutil.copytree(src, tmp, ignore=shutil.ignore_patterns("selection.json", "best"))
    tmp.rename(dst)


def dips_line(dips: dict) -> str:
    """One line on the Done dips of an experiment's finished jobs."""
    w = dips["with_dips"]
    head = (
        f"Done dips (fewer than {100 * DIP_DONE_SHARE:.0f} % of training episodes ending with Done): "
        f"{len(w)} of {dips['jobs']} jobs"
    )
    if not w:
        return head + "."
    parts = []
    for x in w:
        spans = ", ".join(
            f"updates {d['start']}-{d['end']}" + ("" if d["recovered"] else " (not recovered)") for d in x["dips"]
        )
        parts.append(f"{x['row']} seed {x['seed']}: {spans}")
    return head + ": " + "; ".join(parts) + "."


def _job_process(cfg: ExperimentConfig, scale: ScaleConfig, index: int, features: str, threads: int) -> dict:
    """One job in a worker process (``--parallel``): training without a progress bar, then evaluation."""
    set_threads(threads)
    exp = Experiment(cfg, train_fn=partial(default_train_fn(), progress_bar=False), scale=scale)
    return exp.run_job(exp.jobs[index], features)


# ---------------------------------------------------------------------------------------------------------
# Command
# ---------------------------------------------------------------------------------------------------------


def add_threads_and_sample(parser: argparse.ArgumentParser) -> None:
    """``--threads`` and ``--sample``, as ``tsnav demo`` takes them (``tsnav experiment``: its config's fields)."""
    add_shared(
        parser,
        "threads",
        help=f"torch CPU threads (default {DEFAULT_THREADS}, or the machine's cores when "
        "fewer: a fixed count, because another count sums floats in another order "
        "and trains another agent)",
    )
    parser.add_argument(
        "--sample",
        action="store_true",
        help="evaluate the agents by sampling their actions instead of the greedy argmax (the default)",
    )


def build_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "experiment",
        metavar="EXPERIMENT|RECIPE.toml",
        help="ablation (Table II), pretraining (Table III), threshold (Fig. 4), or a recipe file "
        "(configs/experiments/*.toml) naming the experiment and its scale",
    )
    parser.add_argument(
        "--build-world",
        action="store_true",
        help="build the scale's world into --data first when the folder does not exist "
        "(small: demo, paper: ithor-real, the real iTHOR scenes)",
    )
    parser.add_argument("--no-report", action="store_true", help="do not write OUT/report/index.html at the end")
    parser.add_argument(
        "--print-recipe",
        action="store_true",
        help="print the resolved recipe (TOML, without this machine's folders) and stop",
    )
    add_shared(
        parser,
        "set",
        help="set one setting of the recipe, e.g. --set scale.train.lr=1e-3 or "
        "--set experiment.seeds=3 (a TOML value; none for None); repeatable",
    )
    add_options(
        parser.add_argument_group("experiment (ExperimentConfig; recipe section [experiment])"),
        ExperimentConfig,
        "experiment",
        exclude=("experiment",),
    )


def resolve(args: argparse.Namespace) -> tuple[ExperimentConfig, ScaleConfig]:
    """The experiment of the command line: a recipe file or an experiment's name, ``--set``, then the options."""
    if args.experiment in EXPERIMENTS:
        recipe = {"experiment": {"experiment": args.experiment}}
    elif args.experiment.endswith(".toml") or Path(args.experiment).exists():
        recipe = read_recipe(args.experiment)
    else:
        raise CommandError(f"{args.experiment!r}: neither an experiment ({', '.join(EXPERIMENTS)}) nor a recipe file")
    recipe = apply_sets(recipe, args.set, RECIPE_SECTIONS)
    recipe = merge(recipe, {"experiment": given(args, "experiment")})
    exp = recipe.get("experiment", {})
    if exp.get("reuse_from"):
        exp["reuse_from"] = [str(Path(d).resolve()) for d in exp["reuse_from"]]
    return resolve_experiment(recipe, need_paths=not args.print_recipe)


def run(args: argparse.Namespace) -> int:
    cfg, scale = resolve(args)
    check_protocol(cfg.protocol)  # a bad name stops here, in one line, before any work
    if args.print_recipe:
        print(
            dump_recipe(
                experiment_recipe(cfg, scale, paths=False),
                header=f"tsnav experiment {cfg.experiment}: {EXPERIMENT_INFO[cfg.experiment]['description']}",
            ),
            end="",
        )
        return 0
    world = scale.world
    if not Path(cfg.data).is_dir() and not (args.build_world and not Path(cfg.data).exists()):
        raise CommandError(
            f"--data {cfg.data}: no such dataset folder (--build-world builds the {world} world of "
            f"--scale {cfg.scale} there; or: tsnav world --preset {world} --out {cfg.data})"
        )
    if args.build_world:
        ensure_world(cfg.data, world, build=True)
    for opt in ("vc1_weights", "resnet18_weights"):
        v = getattr(cfg, opt)
        if v and not Path(v).exists():
            raise CommandError(f"--{opt.replace('_', '-')} {v}: no such file")
    for d in cfg.reuse_from:
        if not (Path(d) / "experiment.json").exists():
            raise CommandError(f"--reuse-from {d}: not an experiment folder (no experiment.json)")
    if cfg.vc1_weights and cfg.experiment != "pretraining":
        raise CommandError("--vc1-weights adds a row to the pretraining experiment only")
    if cfg.threads is not None and cfg.threads < 1:
        raise CommandError("--threads must be >= 1")
    exp = Experiment(cfg, scale=None if same_scale(scale, SCALES[cfg.scale]) else scale)
    say(f"torch threads: {set_threads(cfg.threads)}")
    results = exp.run()
    print(markdown_table(results))
    if results.get("welch"):
        print(welch_markdown(results))
    print(
        f"tables: {exp.out / 'table.md'}, {exp.out / 'table.csv'}"
        + (f", plot {exp.out / 'threshold.png'}" if cfg.experiment == "threshold" else "")
    )
    if not args.no_report:
        print(f"report: {build_report(exp.out)}")
    return 0
