"""``tsnav demo``: the main job, end to end on the embedded world, in about 5 minutes of an idle 2-core CPU.

Steps (each prints progress; each is skipped on a second run when its marker ``OUT/steps/<step>/DONE`` exists and
its outputs are still there - folders of earlier versions, with ``OUT/stages/<step>.json``, are resumed from
those - and every underlying step resumes after an interruption):

 1. world        build the ``demo-real-small`` preset: 16 of the real iTHOR rooms               OUT/world
                 (``ithor-real``; 8 train, 4 val, 4 test; 128x128 frames); ``--preset demo-real``
                 is the longer demo of 28 rooms
 2. pretrain     DE-MAE on the training frames (ViT-Tiny, 64x64, one thread), while a process of OUT/pretrain/demae
                 its own writes the shipped detector's tables (step 5) on the other core
 3. features     cache the encoder's features of the training, val and test rooms once (one      */features_demae-<fp>.hdf5
                 process per core, :mod:`tsnav.scene_pool`)
 4. detector     the learned detector (issue 14): by default the one shipped with tsnav         (package) or OUT/detector
                 (:mod:`tsnav.detect.shipped`, trained on the 80 ithor-real training rooms, as
                 the paper's DETR is trained apart from the agent); ``--detector train`` trains
                 one here on the training rooms for a fixed number of steps (one thread: the same
                 detector on any machine), calibrated on val (the only choice for 64-px worlds)
 5. detections   its per-state table in every room (its confidence drives the stage switch and  world/*/detections_learned.hdf5
                 its boxes and features feed the agent); quality on the val rooms printed      OUT/detector_quality.json
                 (``--detections oracle``: the oracle's table instead, no detector used)
 6. episodes     fixed test episodes under each success protocol (:mod:`tsnav.protocol`: the   OUT/test_episodes.json,
                 paper's 1.0 m rule, and the lineage's 1.5 m visibility map with its             OUT/test_episodes_lineage.json,
                 start-success episodes), and val episodes for checkpoint selection under the    OUT/val_episodes*.json
                 training protocol (``--protocol``, default paper)
 7. train        a TSRM agent with the batched A2C trainer (on demo-real-small 300 updates of    OUT/run
                 128 episodes over two processes, about two minutes; on demo-real 1000 updates
                 of 64 in one); its milestones scored greedily on the val episodes, the best
                 kept as OUT/run/best and evaluated
 8. evaluate     the agent, the same agent reading the oracle's table instead of the learned   OUT/eval/<policy>,
                 one, the scripted explorer and the random policy on the test episodes, under   OUT/eval/<policy>_lineage
                 both protocols (the ``paper`` rows are the demo's table from before protocols)
 9. shipped      the agent that ships with tsnav (``tsnav release``'s default, 1.5 M training     OUT/eval/shipped,
                 episodes on the 80 real training rooms) on the same test episodes, greedy,     OUT/eval/shipped_lineage
                 under both protocols, so that the table shows what the project's agent does
                 beside two minutes of training: its detector's tables and its encoder's
                 features in the test rooms (written by the background process of step 2 after
                 the demo's tables), then the evaluation (``--no-shipped`` leaves it out;
                 128-px ithor-real worlds only)
10. report       HTML report: tables, curves, reconstructions, episode gallery with clips       OUT/report/index.html

The training and pretraining use the training rooms, linked into ``OUT/train_world`` (``train_rooms_per_type``
keeps only the smallest ones per room type, for shorter runs); the val and test rooms are never seen in training.

The demo is the ``demo`` experiment (:mod:`tsnav.pipeline.experiment`): one row of the paper's (TSRM + DE-MAE) at the
``demo`` scale (:data:`tsnav.pipeline.config.SCALES`), run as a job list of the experiments
(:class:`~tsnav.pipeline.experiment.JobList`, ``DONE`` markers). Its encoder, feature cache, detection tables,
training and checkpoint selection are the experiment's (:class:`~tsnav.pipeline.experiment.Experiment`); what the
demo adds is the world, the scripted baselines and the shipped agent beside the agent under both protocols, and the
printed table.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from dataclasses import asdict, dataclass
from typing import ClassVar
from pathlib import Path

from ..constants import C_TARGET
from ..data.detections import read_fingerprint
from ..data.reader import list_scenes, load_scene
from ..distributed import spawn_context
from ..atomic import atomic_write_text
from ..detect.train import DetectorTrainConfig
from ..errors import CommandError
from ..pretrain.train import PretrainConfig
from ..rl.config import TrainConfig
from ..settings import (
    add_options,
    add_shared,
    apply_sets,
    build,
    dump_recipe,
    field_docs,
    given,
    merge,
    read_recipe,
    to_recipe,
)
from .recipes import JOB_FIELDS
from .experiment import SELECT_SEED, Experiment, JobList, Step, add_threads_and_sample, set_threads
from .config import DEMO, DETECTOR_SOURCES, QUICK_DEMO_PRESET, ExperimentConfig, ScaleConfig, demo_scale
from ..report.html import build_report
from ..eval.runner import evaluate_to_folder
from ..detect.shipped import DEFAULT_SHIPPED, shipped_meta
from ..detect.train import is_checkpoint, read_meta
from .detector_steps import (
    complete_tables,
    ensure_detector,
    ensure_shipped_detections,
    one_thread,
    record_quality,
    tables_complete,
)
from ..report.tables import quality_line
from .steps import encoder_spec, ensure_episodes, ensure_oracle_detections, episodes_name
from .release import agent_folder, ensure_release_detections, ensure_release_features, headline, read_card
from ..metrics import METRICS, write_json
from ..protocol import DEFAULT_PROTOCOL, PROTOCOLS, check_protocol, protocol_line
from ..pretrain.train import read_progress
from ..rl.logger import read_log
from ..sim.episodes import read_episodes
from ..world.build import BuildConfig, build_dataset
from ..world.presets import preset_scenes

#: The demo's steps, in order (the pipeline's steps; "stage" names the paper's searching / pathfinding stages).
STEPS = (
    "world",
    "pretrain",
    "features",
    "detector",
    "detections",
    "episodes",
    "train",
    "evaluate",
    "shipped",
    "report",
)


@dataclass
class DemoConfig:
    """The demo: a world preset and the ``demo`` scale of the experiments (on ``demo-real-small``, about 5 minutes of an
    idle 2-core CPU; on ``demo-real`` about 13)."""

    preset: str = QUICK_DEMO_PRESET
    """World preset (``tsnav world --preset``): ``demo-real-small`` (16 real iTHOR rooms at 128x128, the quick
    demo), ``demo-real`` (28 real rooms, the demo of before issue 26) or ``demo`` (20 procedural rooms at 64x64,
    with ``detector="train"``)."""
    world_workers: int = 2
    """Processes building the world."""
    train_rooms_per_type: int | None = None
    """Training rooms used per room type (the smallest ones); None: all training rooms."""
    scale: ScaleConfig | None = None
    """Sizes of pretraining, training and evaluation; None: :func:`~tsnav.pipeline.config.demo_scale` of the
    preset (``SCALES["demo"]``: ViT-Tiny at 64x64, 300 DE-MAE steps, ``DEMO_UPDATES`` updates of batched A2C, 100
    test episodes per room type; on ``demo-real-small`` ``QUICK_DEMO_UPDATES`` updates). Read the sizes in use
    through :attr:`sizes`: None stays None, so that ``dataclasses.replace(cfg, preset=...)`` takes the new
    preset's sizes."""
    detections: str = "learned"
    """Detection tables the agent and the stage switch read, named explicitly (the agent never falls back to
    ground truth): ``learned`` (issue 14 item 4: the learned detector's, shipped or trained here, see ``detector``) or
    ``oracle`` (computed here; its features carry no distance, its confidence is a hand-made function of
    instance size and distance)."""
    detector: str = "shipped"
    """Where the learned detector comes from: ``shipped`` (:mod:`tsnav.detect.shipped`, 128-px worlds) or
    ``train`` (trained here on the training rooms, ``scale.detector.steps`` steps)."""
    seed: int = 0
    """Seed of the training run and of the random policy."""
    gallery: int = 6
    """Episodes shown per evaluation in the report."""
    sample: bool = False
    """Evaluate the agent by sampling its actions instead of the greedy argmax (the lineage's test-time rule)."""
    protocol: str = DEFAULT_PROTOCOL
    """Success protocol the agent is trained and its checkpoint selected under (:mod:`tsnav.protocol`); every
    policy is evaluated under both protocols either way."""

    shipped: bool = True
    """Evaluate the agent that ships with tsnav (:mod:`tsnav.pipeline.release`) on the same test episodes, beside
    the demo's own agent (its step ``shipped``); left out on worlds it cannot read (not ``ithor-real`` at its frame
    size, or rooms of another rules version)."""
    shipped_agent: str | None = None
    """The shipped agent of that row: a name of ``tsnav release list`` or an agent folder; None: the default one."""

    tables_beside_pretraining: bool | None = None
    """Write the shipped detector's tables in a process of their own while DE-MAE pretrains on one thread; None:
    on the quick demo's world only (on the others pretraining keeps the demo's threads, and so their encoders).
    Read through :attr:`tables_beside`."""

    #: Allowed values of fields (the command-line options' choices, :mod:`tsnav.settings`).
    CHOICES: ClassVar[dict] = {
        "preset": (QUICK_DEMO_PRESET, "demo-real", "demo"),
        "detections": ("learned", "oracle"),
        "detector": DETECTOR_SOURCES,
        "protocol": PROTOCOLS,
    }

    def __post_init__(self):
        for name, allowed in self.CHOICES.items():  # the preset: any world preset (tests build tiny ones)
            if name != "preset" and getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if self.world_workers < 1:
            raise ValueError(f"world_workers must be >= 1, got {self.world_workers}")

    @property
    def sizes(self) -> ScaleConfig:
        """The sizes in use: :attr:`scale`, or the preset's (:func:`~tsnav.pipeline.config.demo_scale`)."""
        return self.scale if self.scale is not None else demo_scale(self.preset)

    @property
    def tables_beside(self) -> bool:
        """:attr:`tables_beside_pretraining`, or whether the preset is the quick demo's."""
        if self.tables_beside_pretraining is not None:
            return self.tables_beside_pretraining
        return self.preset == QUICK_DEMO_PRESET


#: The demo's short options for settings of its scale (``[scale]``) and of its config (``[demo]``): option ->
#: recipe key; the help is the setting's own. ``--train-updates`` or ``--train-minutes`` replaces the whole
#: budget (the other one none).
SHORTHANDS = {
    "workers": "demo.world_workers",
    "train_updates": "scale.train.updates",
    "train_minutes": "scale.train.minutes",
    "pretrain_steps": "scale.pretrain.steps",
    "procs": "scale.train.procs",
    "detector_steps": "scale.detector.steps",
}
#: The sections of the demo's recipe (``configs/demo.toml``).
SECTIONS = ("demo", "scale")


def build_parser(p: argparse.ArgumentParser) -> None:
    add_shared(p, "out", default="out/demo", help="folder for the world, runs and report (default out/demo)")
    add_shared(
        p,
        "config",
        help="the demo's recipe (configs/demo.toml): [demo] and [scale] sections; options given here override it",
    )
    add_shared(p, "set", help="set one setting, e.g. --set scale.train.lr=1e-3 (a TOML value); repeatable")
    p.add_argument("--print-recipe", action="store_true", help="print the resolved recipe (TOML) and stop")
    add_threads_and_sample(p)
    add_options(p, DemoConfig, "demo", exclude=("scale", "sample", "world_workers"))
    for option, key in SHORTHANDS.items():
        section, *path = key.split(".")
        cls = (
            DemoConfig
            if section == "demo"
            else {"train": TrainConfig, "pretrain": PretrainConfig, "detector": DetectorTrainConfig}[path[0]]
        )
        doc = field_docs(cls).get(path[-1], "")
        p.add_argument(
            "--" + option.replace("_", "-"),
            dest=f"shorthand.{option}",
            type=int if option != "train_minutes" else float,
            default=None,
            metavar="N",
            help=f"{key}: {doc} (default: the preset's scale; demo_scale)".replace("%", "%%"),
        )


def resolve(args: argparse.Namespace) -> DemoConfig:
    """The demo's config of the command line: ``--config``, ``--set``, the options (:data:`SHORTHANDS` too)."""
    recipe = apply_sets(read_recipe(args.config) if args.config else {}, args.set, SECTIONS)
    unknown = sorted(set(recipe) - set(SECTIONS))
    if unknown:
        raise CommandError(
            f"{args.config}: no section {', '.join(unknown)} in the demo's recipe (sections: {', '.join(SECTIONS)})"
        )
    short = {}
    for option, v in given(args, "shorthand").items():
        short = merge(short, apply_sets({}, [f"{SHORTHANDS[option]}={v!r}"]))
    train = short.get("scale", {}).get("train", {})
    if "updates" in train or "minutes" in train:  # asked for: replaces the default budget
        train.setdefault("updates", None)
        train.setdefault("minutes", None)
    recipe = merge(recipe, short, {"demo": given(args, "demo")})
    if args.sample:
        recipe["demo"]["sample"] = True
    cfg = build(DemoConfig, recipe.get("demo") or {}, "demo")
    if recipe.get("scale"):
        cfg.scale = build(ScaleConfig, _nones(recipe["scale"]), "scale", base=cfg.sizes)
    return cfg


def _nones(d: dict) -> dict:
    """A section with Python None kept as the recipe's none (short options given as None)."""
    return {k: _nones(v) if isinstance(v, dict) else ("none" if v is None else v) for k, v in d.items()}


# ---------------------------------------------------------------------------------------------------------
# Steps
# ---------------------------------------------------------------------------------------------------------


def train_subset(world: Path, dest: Path, per_type: int | None) -> list[str]:
    """Link the ``per_type`` smallest training rooms of each room type into ``dest`` (a dataset root of its own);
    returns their names. None: every training room."""
    rooms: dict[str, list[tuple[int, str, Path]]] = {}
    for p in list_scenes(world, "train"):
        s = load_scene(p)
        rooms.setdefault(s.room_type, []).append((s.num_states, s.name, p))
    chosen = []
    for rt in sorted(rooms):
        chosen += sorted(rooms[rt])[:per_type] if per_type else sorted(rooms[rt])
    dest.mkdir(parents=True, exist_ok=True)
    names = {n for _, n, _ in chosen}
    for old in dest.iterdir():
        if old.is_symlink() and old.name not in names:
            old.unlink()
    for _, n, p in chosen:
        link = dest / n
        if not link.exists():
            link.symlink_to(p.resolve(), target_is_directory=True)
    return sorted(names)


class DemoExperiment(Experiment):
    """The ``demo`` experiment in the demo's folder layout: its one job's run is ``OUT/run``, its evaluation
    ``OUT/eval/agent``, its checkpoint-selection episodes ``OUT/val_episodes*.json``."""

    writes_recipe = False  # the demo's own recipe.toml ([demo], [scale]) is written by run_demo

    def train_dir(self, job) -> Path:
        return self.out / "run"

    def eval_dir(self, job, protocol: str | None = None) -> Path:
        """The agent's evaluation folder under ``protocol``, named as :meth:`Demo.folder` names it (``eval/agent``
        for the paper protocol; None: that one, as before protocols)."""
        p = protocol or DEFAULT_PROTOCOL
        return self.out / "eval" / ("agent" if p == DEFAULT_PROTOCOL else f"agent_{p}")

    @property
    def other_protocols(self) -> list[str]:
        """None: the demo evaluates every policy under every protocol itself (its evaluate step)."""
        return []

    @property
    def select_file(self) -> Path:
        return self.out / episodes_name("val", self.cfg.protocol)


def check_demo(out: Path, cfg: DemoConfig) -> None:
    """Refuse, in one line and before any work, what the demo cannot run: an unknown detector source, the shipped
    detector on a world of another frame size, a folder holding another preset's world."""
    check_protocol(cfg.protocol)
    if cfg.detector not in DETECTOR_SOURCES:
        raise CommandError(f"unknown detector source {cfg.detector!r} (choose from {', '.join(DETECTOR_SOURCES)})")
    if cfg.detections != "oracle" and cfg.detector == "shipped":
        size, want = BuildConfig.from_preset(cfg.preset).image_size, shipped_meta()["model"]["image_size"]
        if size != want:
            raise CommandError(
                f"the shipped detector reads {want}x{want} frames (the ithor-real rooms), the "
                f"{cfg.preset} world has {size}x{size}: use --detector train, or --preset {QUICK_DEMO_PRESET}"
            )
    index = out / "world" / "index.json"
    if index.exists():  # a world of another preset is never mixed with this one (names overlap): refused
        try:
            was = json.loads(index.read_text()).get("preset")
        except ValueError:
            was = None
        if was != cfg.preset:
            raise CommandError(
                f"{out / 'world'} holds the {was!r} world, not {cfg.preset!r}: use another --out (or --preset {was})"
            )


class Demo:
    """The demo's steps over its experiment (:class:`DemoExperiment`, one job) and its folder ``out``."""

    def __init__(self, out: Path, cfg: DemoConfig, train_fn=None):
        self.out, self.cfg, self.sc = out, cfg, cfg.sizes
        self.world, self.sub, self.det_dir = out / "world", out / "train_world", out / "detector"
        self.exp = DemoExperiment(
            ExperimentConfig(
                experiment=DEMO,
                data=str(self.world),
                train_data=str(self.sub),
                out=str(out),
                scale="demo",
                detections=cfg.detections,
                detector=cfg.detector,
                detector_dir=str(self.det_dir),
                device="cpu",
                sample=cfg.sample,
                protocol=cfg.protocol,
                seed_offset=cfg.seed,
            ),
            train_fn=train_fn,
            scale=cfg.sizes,
        )
        self.job = self.exp.jobs[0]
        self.es = encoder_spec(self.job.row.encoder, self.sc, self.exp.pretrain_dir, self.exp.cfg)
        self.ep_files = {p: out / episodes_name("test", p) for p in PROTOCOLS}
        self.val_file = self.exp.select_file
        self.run_dir = self.exp.train_dir(self.job)
        self.policies = eval_policies(cfg.detections)
        self.results: dict[str, dict] = {}
        self.background = None  # the process writing detection tables during pretraining
        self.background_tables = None  # set by it when the demo's own tables are written
        self.wrote_in_background = False
        self.shipped_folder, self.shipped_card, self.shipped_why = shipped_agent(cfg)
        self.jobs = JobList(self.steps(), say=lambda m: print(m, flush=True))

    def step(self, name: str, what: str, run, valid=lambda m: True, show=None) -> Step:
        return Step(
            name, what, self.out / "steps" / name, run, valid, show, legacy=self.out / "stages" / f"{name}.json"
        )

    def steps(self) -> list[Step]:
        cfg, sc, es = self.cfg, self.sc, self.es
        learned, shipped = cfg.detections != "oracle", cfg.detector == "shipped"
        if not learned:
            detector = self.step("detector", "not used (--detections oracle)", None)
        elif shipped:
            detector = self.step(
                "detector",
                f"learned detector shipped with tsnav ({DEFAULT_SHIPPED}; trained on the "
                "ithor-real training rooms apart from the agent, as the paper's DETR): nothing "
                "trained here",
                self.detector,
                self.detector_ok,
            )
        else:
            detector = self.step(
                "detector",
                f"learned detector, {sc.detector.steps} steps on the training rooms (one "
                f"thread), temperature fitted on the val rooms -> {self.det_dir}",
                self.detector,
                self.detector_ok,
            )
        what = "the learned detector's table per room" if learned else "the oracle detector's table per room"
        budget = ", ".join(f"{v:g} {k}" for k, v in sc.budget.items() if v is not None) or "1.5 M episodes"
        return [
            self.step(
                "world",
                f"build the `{cfg.preset}` world into {self.world} (finished rooms are reused)",
                self.build_world,
                self.world_ok,
                lambda m: print(f"    {m['scenes']} rooms; training on {', '.join(m['train_rooms'])}", flush=True),
            ),
            self.step(
                "pretrain",
                f"DE-MAE, {sc.pretrain.model} at {sc.pretrain.img_size}x{sc.pretrain.img_size}, "
                f"{sc.pretrain.steps} steps -> {es.spec}",
                self.pretrain,
                lambda m: (Path(es.spec) / "encoder.safetensors").exists(),
            ),
            self.step(
                "features",
                "encode every state of the training, validation and test rooms once",
                self.features,
                self.features_ok,
            ),
            detector,
            self.step(
                "detections",
                f"detections: {cfg.detections} (named explicitly), {what} (confidence drives the "
                f"stage switch, C_target {C_TARGET:g}); quality on the val rooms",
                self.detections,
                lambda m: (
                    "quality" in m
                    and all(
                        read_fingerprint(p, cfg.detections) == m.get("fingerprint") for p in list_scenes(self.world)
                    )
                ),
            ),
            self.step(
                "episodes",
                f"{sc.test_per_room_type} test episodes per room type under each protocol "
                f"({', '.join(PROTOCOLS)}) and {sc.val_per_room_type} validation episodes per room type ("
                f"{cfg.protocol})",
                self.episodes,
                lambda m: (
                    all(f.exists() for f in self.ep_files.values()) and self.val_file.exists() and "by_protocol" in m
                ),
                self.show_episodes,
            ),
            self.step(
                "train",
                f"TSRM agent, batched A2C, {budget}, best milestone on validation -> {self.run_dir}",
                self.train,
                lambda m: (
                    m.get("budget") == sc.budget and "checkpoint" in m and (self.run_dir / "config.json").exists()
                ),
            ),
            self.step(
                "evaluate",
                "on the test episodes of each protocol: " + ", ".join(lab for lab, _, _ in self.policies),
                self.evaluate,
                self.evaluate_ok,
            ),
            self.shipped_step(),
            self.step(
                "report",
                f"HTML report -> {self.out / 'report' / 'index.html'}",
                self.report,
                lambda m: (self.out / "report" / "index.html").exists(),
            ),
        ]

    # 1. world -------------------------------------------------------------------------------------------
    def build_world(self) -> dict:
        build_dataset(self.world, self.cfg.preset, workers=self.cfg.world_workers)
        names = train_subset(self.world, self.sub, self.cfg.train_rooms_per_type)
        return {"scenes": len(list_scenes(self.world)), "train_rooms": names}

    def world_ok(self, m: dict) -> bool:
        return (
            self.world.is_dir()
            and len(list_scenes(self.world)) == len(preset_scenes(self.cfg.preset))
            and self.sub.is_dir()
        )

    # 2. pretrain, 3. features ---------------------------------------------------------------------------
    def pretrain(self) -> dict:
        """DE-MAE on one thread while another process writes the shipped detector's tables on the other core (the
        two need only the world; pretraining gains nothing from a second thread); the detections step then finds
        them written, or writes what is missing."""
        if self.start_background_tables():
            with one_thread():  # the other core writes the tables
                self.exp.encoder(self.job.row.encoder)
        else:
            self.exp.encoder(self.job.row.encoder)
        prog = read_progress(self.es.spec)
        return {"steps": prog["step"], "loss": prog.get("loss")}

    def start_background_tables(self) -> bool:
        """Start writing the shipped detector's missing tables in a process of its own (one thread) when
        ``tables_beside_pretraining``, and after them what the shipped agent's row needs in the test rooms (its
        detector's tables, its encoder's features); returns whether it started."""
        if (
            self.cfg.detections == "oracle"
            or self.cfg.detector != "shipped"
            or self.background is not None
            or not self.cfg.tables_beside
        ):
            return False
        ctx = spawn_context()
        self.background_tables = ctx.Event()
        agent = str(self.shipped_folder) if self.shipped_folder is not None else None
        self.background = ctx.Process(
            target=write_tables_quietly,
            args=(str(self.world), self.cfg.detections),
            kwargs={"done": self.background_tables, "shipped": agent},
            daemon=True,
        )
        self.background.start()
        return True

    def join_background_tables(self, everything: bool = False) -> None:
        """Wait for the tables' process to have written the demo's tables (``everything``: until it ends, the
        shipped agent's files written too); a failure there is said in one line (the step that needs the files
        then writes what is missing itself, and a real problem is raised there)."""
        if self.background is None:
            return
        while not everything and not self.background_tables.wait(0.5) and self.background.is_alive():
            pass
        if self.background_tables.is_set():
            self.wrote_in_background = True
            if not everything:
                return
        self.background.join()
        if self.background.exitcode != 0:
            print(
                f"    the detection tables' background process failed (exit code {self.background.exitcode}); "
                "writing the missing files here",
                flush=True,
            )
        self.background = None

    def features(self) -> dict:
        name = self.exp.features(self.es, ["train", "test", "val"])
        return {
            "name": name,
            "scenes": sum(
                len(list_scenes(d, s)) for d, s in ((self.sub, "train"), (self.world, "test"), (self.world, "val"))
            ),
        }

    def features_ok(self, m: dict) -> bool:
        rooms = list_scenes(self.sub, "train") + list_scenes(self.world, "test") + list_scenes(self.world, "val")
        return "name" in m and all((p / f"features_{m['name']}.hdf5").exists() for p in rooms)

    # 4. detector, 5. detections -------------------------------------------------------------------------
    def detector(self) -> dict:
        cfg = self.cfg
        self.join_background_tables()
        ready = complete_tables(self.world, cfg.detections, cfg.detector)  # the one rule on foreign tables
        if (
            ready and not self.wrote_in_background
        ):  # every room already has a learned table (e.g. written by an experiment): used as it is
            print(
                f"    every room already holds detections_{cfg.detections}.hdf5 ({ready}): no detector trained",
                flush=True,
            )
            return {"fingerprint": ready, "tables": "existing"}
        if cfg.detector == "shipped":  # loaded (and its weights checked) by the detections step
            meta = shipped_meta()
            if self.wrote_in_background:
                print("    its tables were written during pretraining, by a process of their own", flush=True)
            print(
                f"    shipped detector {DEFAULT_SHIPPED}: step {meta['step']}, trained on "
                f"{len(meta['train_scenes'])} ithor-real training rooms, temperature {meta['temperature']:.3f} "
                f"({meta['fingerprint']})",
                flush=True,
            )
            return {
                "fingerprint": meta["fingerprint"],
                "source": "shipped",
                "steps": meta["step"],
                "temperature": meta["temperature"],
            }
        det = ensure_detector(self.sub, self.world, self.det_dir, self.sc, say=lambda m: print(m, flush=True))
        return {
            "fingerprint": det.fingerprint,
            "source": "train",
            "steps": det.meta.get("step"),
            "temperature": det.temperature,
        }

    def detector_ok(self, m: dict) -> bool:
        if m.get("tables") == "existing":
            return tables_complete(self.world, self.cfg.detections) == m.get("fingerprint")
        if self.cfg.detector == "shipped":
            return m.get("source") == "shipped" and m.get("fingerprint") == shipped_meta()["fingerprint"]
        if m.get("source", "train") != "train":  # markers written before the shipped detector have no source
            return False
        meta = read_meta(self.det_dir) if is_checkpoint(self.det_dir) else {}
        return meta.get("step") == self.sc.detector.steps and meta.get("calibrated_step") == self.sc.detector.steps

    def detections(self) -> dict:
        self.join_background_tables()
        done = self.exp.ensure_detections(self.cfg.detections)
        quality = record_quality(self.out, self.world, [self.cfg.detections], say=lambda m: print(m, flush=True))
        return {"written": done["written"], "fingerprint": done["fingerprint"], "quality": quality[self.cfg.detections]}

    # 6. episodes ----------------------------------------------------------------------------------------
    def episodes(self) -> dict:
        sc = self.sc
        for p, f in self.ep_files.items():
            ensure_episodes(self.world, "test", f, sc.test_per_room_type, protocol=p)
        ensure_episodes(
            self.world, "val", self.val_file, sc.val_per_room_type, seed=SELECT_SEED, protocol=self.cfg.protocol
        )
        test = {p: read_episodes(f)[0] for p, f in self.ep_files.items()}
        return {
            "episodes": len(test[DEFAULT_PROTOCOL]),
            "val_episodes": len(read_episodes(self.val_file)[0]),
            "by_protocol": {
                p: {"episodes": len(e), "start_success": sum(x.optimal_length == 0 for x in e)} for p, e in test.items()
            },
        }

    def show_episodes(self, m: dict) -> None:
        for p, f in self.ep_files.items():
            b = m["by_protocol"][p]
            print(
                f"    {p}: {b['episodes']} test episodes in {f}"
                + (f" ({b['start_success']} start already succeeds)" if b["start_success"] else ""),
                flush=True,
            )
        print(
            f"    {m['val_episodes']} in {self.val_file} (checkpoint selection, protocol {self.cfg.protocol})",
            flush=True,
        )

    # 7. train -------------------------------------------------------------------------------------------
    def train(self) -> dict:
        """The experiment's job: trained, then its milestones scored greedily on the val rooms' episodes and the
        best kept as run/best (resumed from run/selection.json when interrupted there)."""
        self.exp.train_job(self.job, self.jobs.markers["features"]["name"])
        log = read_log(self.run_dir)
        last = {k: log[-1][k] for k in ("update", "env_steps", "episodes", "SR") if log and k in log[-1]}
        checkpoint = self.exp.choose_checkpoint(self.job)
        print(
            f"    best of {checkpoint['candidates']} checkpoints on validation: {checkpoint['name']} (update "
            f"{checkpoint['update']}, SR {100 * checkpoint['val_SR']:.1f}, SPL {100 * checkpoint['val_SPL']:.1f})",
            flush=True,
        )
        return {"budget": self.sc.budget, "log_lines": len(log), **last, "checkpoint": checkpoint}

    # 8. evaluate ----------------------------------------------------------------------------------------
    def folder(self, name: str, protocol: str) -> Path:
        return self.out / "eval" / (name if protocol == DEFAULT_PROTOCOL else f"{name}_{protocol}")

    def evaluate(self) -> dict:
        cfg = self.cfg
        if any(det == "oracle" for _, _, det in self.policies):
            ensure_oracle_detections(self.world, "oracle")
        for p in PROTOCOLS:
            for label, name, det in self.policies:
                print(f"    {label} ({p}) ...", flush=True)
                agent = name.startswith("agent")
                self.results.setdefault(p, {})[label] = evaluate_to_folder(
                    self.folder(name, p),
                    self.world,
                    self.ep_files[p],
                    policy="agent" if agent else name,
                    run=self.run_dir if agent else None,
                    detections=det or cfg.detections,
                    seed=cfg.seed,
                    label=label if p == DEFAULT_PROTOCOL else f"{label} [{p}]",
                    sample=cfg.sample,
                    protocol=p,
                )
        return {"policies": [n for _, n, _ in self.policies], "protocols": list(PROTOCOLS), "sample": cfg.sample}

    def evaluate_ok(self, m: dict) -> bool:
        return (
            m.get("policies") == [n for _, n, _ in self.policies]
            and m.get("sample", True) == self.cfg.sample
            and m.get("protocols") == list(PROTOCOLS)
            and all((self.folder(n, p) / "metrics.json").exists() for _, n, _ in self.policies for p in PROTOCOLS)
        )

    def read_results(self) -> dict[str, dict]:
        """The evaluations' summaries: protocol -> label -> summary, in the table's order (the demo's agent, the
        shipped agent, the others); those of steps that were reused are read back from their folders."""
        rows = [(label, name) for label, name, _ in self.policies]
        if self.shipped_folder is not None:
            rows.insert(1, (self.shipped_label, "shipped"))
        for p in PROTOCOLS:
            have = self.results.get(p, {})
            ordered = {}
            for label, name in rows:
                path = self.folder(name, p) / "metrics.json"
                if label in have:
                    ordered[label] = have[label]
                elif path.exists():
                    ordered[label] = json.loads(path.read_text())["metrics"]
            self.results[p] = ordered
        return self.results

    # 9. shipped -----------------------------------------------------------------------------------------
    @property
    def shipped_label(self) -> str:
        return f"shipped agent ({self.shipped_folder.name})" if self.shipped_folder is not None else ""

    def shipped_step(self) -> Step:
        if self.shipped_folder is None:
            return self.step("shipped", f"the agent that ships with tsnav: {self.shipped_why}", None)
        card = self.shipped_card
        return self.step(
            "shipped",
            f"{self.shipped_folder.name}, the agent that ships with tsnav, on the same test "
            f"episodes: its detector's ({card['detector_shipped']}) tables and its encoder's features in "
            "the test rooms, then greedy under each protocol",
            self.shipped,
            self.shipped_ok,
        )

    def shipped(self) -> dict:
        """The shipped agent on the demo's test episodes (greedy, as ``tsnav release eval``), under each protocol
        named explicitly (it was trained under its card's)."""
        folder, card = self.shipped_folder, self.shipped_card
        self.join_background_tables(everything=True)
        version = int(card.get("world_version") or 1)
        have = room_versions(self.world, "test")
        if have != {version}:
            why = (
                f"the test rooms are of ithor-real rules version {', '.join(map(str, sorted(have)))}, "
                f"{folder.name} was trained on version {version}"
            )
            print(f"    left out: {why}", flush=True)
            return {"agent": folder.name, "skipped": why, **self.shipped_identity()}
        say = lambda m: print(m, flush=True)  # noqa: E731
        ensure_release_detections(self.world, card, split="test", say=say)
        ensure_release_features(self.world, folder, card, split="test")
        for p in PROTOCOLS:
            print(f"    {self.shipped_label} ({p}) ...", flush=True)
            label = self.shipped_label if p == DEFAULT_PROTOCOL else f"{self.shipped_label} [{p}]"
            self.results.setdefault(p, {})[self.shipped_label] = evaluate_to_folder(
                self.folder("shipped", p),
                self.world,
                self.ep_files[p],
                run=str(folder),
                checkpoint="best",
                detections=card["detections"],
                label=label,
                protocol=p,
            )
        return {"agent": folder.name, "protocols": list(PROTOCOLS), **self.shipped_identity()}

    def shipped_identity(self) -> dict:
        """What makes the shipped row another one: the agent's name, policy update and encoder fingerprint."""
        c = self.shipped_card
        return {"policy_update": c.get("policy_update"), "encoder_fingerprint": c.get("encoder_fingerprint")}

    def shipped_ok(self, m: dict) -> bool:
        if m.get("agent") != self.shipped_folder.name or any(m.get(k) != v for k, v in self.shipped_identity().items()):
            return False
        return bool(m.get("skipped")) or all((self.folder("shipped", p) / "metrics.json").exists() for p in PROTOCOLS)

    def shipped_note(self) -> str:
        """A line under the table: which agent each agent row is."""
        if self.shipped_folder is None or not any(self.shipped_label in r for r in self.results.values()):
            return ""
        trained = json.loads((self.shipped_folder / "config.json").read_text())["train"].get("protocol", "paper")
        budget = ", ".join(f"{v:g} {k}" for k, v in self.sc.budget.items() if v is not None)
        return (
            f"{self.policies[0][0]}: this demo's agent ({budget}, trained under {self.cfg.protocol}); "
            f"{self.shipped_label}: the agent that ships with tsnav, trained under {trained} (update "
            f"{self.shipped_card.get('policy_update', '?')}; its card: {headline(self.shipped_card)}; "
            f"`tsnav release eval` evaluates it on all the real test rooms)"
        )

    # 9. report ------------------------------------------------------------------------------------------
    def report(self) -> dict:
        shown = [self.folder("agent", DEFAULT_PROTOCOL)]
        if self.shipped_folder is not None and (self.folder("shipped", "lineage") / "metrics.json").exists():
            shown.append(self.folder("shipped", "lineage"))  # under the protocol it was trained under
        shown += [self.folder("explorer", DEFAULT_PROTOCOL)]
        index = build_report(
            self.out,
            self.out / "report",
            gallery=self.cfg.gallery,
            title=f"tsnav demo: TSRM + DE-MAE on the {self.cfg.preset} world",
            gallery_evals=shown,
        )
        return {"index": str(index)}


def write_tables_quietly(world: str, name: str, done=None, shipped: str | None = None) -> None:
    """The shipped detector's missing tables ``detections_<name>.hdf5`` in every room of ``world``, one thread, no
    output (the demo's background process; the detections step prints their quality); then ``done`` (an event) is
    set and, for the ``shipped`` agent folder, its detector's tables and its encoder's features are written into
    the test rooms (the shipped step then only evaluates)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the demo's: it stops this process (SIGTERM)
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))  # unwinds: no temp files left
    set_threads(1)
    ensure_shipped_detections(world, name, progress=False, say=lambda m: None, workers=1)
    if done is not None:
        done.set()
    if shipped is not None:
        card = read_card(shipped)
        if room_versions(Path(world), "test") == {int(card.get("world_version") or 1)}:
            ensure_release_detections(Path(world), card, split="test", say=lambda m: None, progress=False, workers=1)
            ensure_release_features(Path(world), Path(shipped), card, split="test", progress=False, workers=1)


def shipped_agent(cfg: DemoConfig) -> tuple[Path | None, dict | None, str]:
    """``(folder, card, "")`` of the shipped agent the demo evaluates beside its own, or ``(None, None, why it is
    left out)``: asked not to, or a world it cannot read (another layout source or frame size than its card's)."""
    if not cfg.shipped:
        return None, None, "left out (--no-shipped)"
    try:
        folder = agent_folder(cfg.shipped_agent)
    except CommandError as e:
        if cfg.shipped_agent is not None:  # named, and not there: the user's mistake, said before any work
            raise
        return None, None, str(e)  # none ships with this copy of tsnav
    card = read_card(folder)
    build = BuildConfig.from_preset(cfg.preset)
    world, size = card.get("world_preset", "ithor-real"), int(card.get("image_size", 128))
    if build.world != world or build.image_size != size:
        return (
            None,
            None,
            (
                f"not on the {cfg.preset} world ({folder.name} reads {world} rooms at {size}x{size}; "
                f"the {QUICK_DEMO_PRESET} and demo-real worlds are such)"
            ),
        )
    return folder, card, ""


def room_versions(world: Path, split: str) -> set[int]:
    """The ithor-real rules versions of the rooms of ``split`` (a room without a recorded version: 1)."""
    out = set()
    for p in list_scenes(world, split):
        gen = json.loads((p / "scene.json").read_text()).get("generator") or {}
        out.add(int(gen.get("version", 1)))
    return out


def demo_recipe(cfg: DemoConfig) -> dict:
    """The demo's resolved recipe: ``[demo]`` (its config) and ``[scale]`` (the sizes in use)."""
    demo = {k: v for k, v in to_recipe(cfg).items() if k != "scale"}
    scale = to_recipe(cfg.sizes)
    scale["train"] = {k: v for k, v in scale["train"].items() if k not in JOB_FIELDS}
    return {"demo": demo, "scale": scale}


def run_demo(out: str | Path, cfg: DemoConfig | None = None, train_fn=None) -> dict:
    """Run the demo into ``out``; returns ``{"steps": {name: (status, seconds)}, "results": {protocol: {label:
    summary}}, "seconds"}``. ``train_fn`` replaces the real trainer (tests only; see :mod:`tsnav.pipeline.experiment`)."""
    cfg, out = cfg or DemoConfig(), Path(out)
    check_demo(out, cfg)
    out.mkdir(parents=True, exist_ok=True)
    write_json(
        out / "demo_config.json",
        {
            **asdict(cfg),
            "scale": asdict(cfg.sizes),  # the sizes in use
            "tables_beside_pretraining": cfg.tables_beside,
        },
    )
    atomic_write_text(
        out / "recipe.toml",
        dump_recipe(demo_recipe(cfg), header="The demo's resolved recipe (tsnav demo --config FILE reruns it)."),
    )
    t_all = time.perf_counter()
    demo = Demo(out, cfg, train_fn)
    markers = demo.jobs.run()
    results, total = demo.read_results(), time.perf_counter() - t_all
    _print_results(
        results,
        demo.jobs.times,
        total,
        markers["report"].get("index", str(out / "report" / "index.html")),
        cfg.protocol,
        demo.shipped_note(),
    )
    print(f"detections: {quality_line(markers['detections']['quality'])}", flush=True)
    return {"steps": demo.jobs.times, "results": results, "seconds": total}


def eval_policies(detections: str) -> list[tuple[str, str, str | None]]:
    """The demo's rows: ``(label, folder name, detection table or None for the demo's own)``: the agent, the
    same agent reading the oracle's table (the detector's cost; left out when the demo already runs on the
    oracle's table), the scripted explorer and the random policy."""
    rows = [("agent (TSRM, DE-MAE)", "agent", None)]
    if detections != "oracle":
        rows.append(("agent on the oracle table", "agent_oracle", "oracle"))
    return rows + [("scripted explorer", "explorer", None), ("random", "random", None)]


def results_table(results: dict[str, dict], trained: str) -> str:
    """The demo's results table: one block per success protocol (``results``: protocol -> label -> summary), each
    headed by its protocol line (:func:`tsnav.protocol.protocol_line`; the agent's rows were trained under
    ``trained``), rows ALL and L>=5 per policy in percent. The ``paper`` block is the table of the demo before
    protocols existed, line for line, below its header."""
    labels = [k for r in results.values() for k in r]
    width = max(len(k) for k in labels) if labels else 10
    lines = []
    for protocol, rows in results.items():
        lines += [
            "\nresults on the test episodes (percent; paper IV-A metrics)",
            f"{protocol_line(protocol)}; agent trained under {trained}",
            f"{'policy':<{width}}  subset " + " ".join(f"{m:>6}" for m in METRICS) + "      K",
        ]
        for label, s in rows.items():
            for sub in ("ALL", "L>=5"):
                m = s[sub]
                lines.append(
                    f"{label:<{width}}  {sub:<6} "
                    + " ".join(f"{100 * m[k]:6.2f}" for k in METRICS)
                    + f" {m['episodes']:6d}"
                )
    return "\n".join(lines)


def _print_results(
    results: dict, times: dict, total: float, index: str, trained: str = DEFAULT_PROTOCOL, note: str = ""
) -> None:
    print("\nstep         status    seconds")
    for name in STEPS:
        status, sec = times.get(name, ("-", 0.0))
        print(f"{name:<12} {status:<8} {sec:8.0f}")
    print(f"{'total':<12} {'':<8} {total:8.0f}")
    print(results_table(results, trained))
    if note:
        print(f"\n{note}")
    print(f"\nreport: {index}")


def run(args) -> int:
    cfg = resolve(args)
    if args.print_recipe:
        print(
            dump_recipe(
                demo_recipe(cfg),
                header="tsnav demo: the TSRM + DE-MAE row at the demo scale, plus the scripted baselines",
            ),
            end="",
        )
        return 0
    if args.threads is not None and args.threads < 1:
        raise CommandError("--threads must be >= 1")
    if cfg.sizes.train.num_envs % cfg.sizes.train.procs:
        raise CommandError(
            f"--procs must be >= 1 and divide the {cfg.sizes.train.num_envs} training episodes per update"
        )
    print(f"tsnav demo -> {args.out} (torch threads: {set_threads(args.threads)})", flush=True)
    run_demo(args.out, cfg)
    return 0
