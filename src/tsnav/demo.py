"""``tsnav demo``: the main job, end to end on the embedded world, in about ten minutes of a 2-core CPU.

Stages (each prints progress; each is skipped on a second run when its marker ``OUT/stages/<stage>.json``
exists and its outputs are still there, and every underlying step resumes after an interruption):

 1. world        build the ``demo-real`` preset: 28 of the real iTHOR rooms (``ithor-real``;   OUT/world
                 16 train, 4 val, 8 test; 128x128 frames)
 2. pretrain     DE-MAE on the training frames (ViT-Tiny, 64x64, a couple of minutes)           OUT/pretrain/demae
 3. features     cache the encoder's features of the training, val and test scenes              */features_demae-<fp>.hdf5
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
 7. train        a TSRM agent with the batched A2C trainer (1000 updates, a few minutes); its    OUT/run
                 milestones (every 200 updates) scored greedily on the val episodes, the best
                 kept as OUT/run/best and evaluated
 8. evaluate     the agent, the same agent reading the oracle's table instead of the learned   OUT/eval/<policy>,
                 one, the scripted explorer and the random policy on the test episodes, under   OUT/eval/<policy>_lineage
                 both protocols (the ``paper`` rows are the demo's table from before protocols)
 9. report       HTML report: tables, curves, reconstructions, episode gallery                  OUT/report/index.html

The training and pretraining use the training rooms, linked into ``OUT/train_world`` (``train_rooms_per_type``
keeps only the smallest ones per room type, for shorter runs); the val and test rooms are never seen in training.

The demo is one row of the paper's experiments (TSRM + DE-MAE, :mod:`tsnav.eval.experiment`) at the ``demo``
scale (:data:`tsnav.eval.experiment_config.SCALES`): its encoder, feature cache, training configuration and
evaluation come from the experiment's own functions (``encoder_spec`` / ``ensure_encoder`` /
``ensure_features`` / ``train_config_for`` / ``evaluate_to_folder``); what the demo adds is the world, the
scripted baselines beside the agent, the stage markers and the printed table.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from .constants import C_TARGET
from .data.detections import read_fingerprint
from .data.reader import list_scenes, load_scene
from .detect.oracle import OracleConfig
from .errors import CommandError
from .eval.experiment import DEFAULT_THREADS, SELECT_SEED, set_threads, train_config_for
from .eval.experiment_config import DEMO_UPDATES, DETECTOR_SOURCES, SCALES, ExperimentConfig, Row, ScaleConfig
from .eval.report import build_report
from .eval.runner import evaluate_to_folder
from .eval.select import chosen, select_checkpoint
from .detect.shipped import DEFAULT_SHIPPED, shipped_meta
from .detect.train import is_checkpoint, read_meta
from .eval.detector_stage import (ensure_detector, ensure_learned_detections, ensure_shipped_detections,
                                  record_quality, tables_complete)
from .eval.tables import quality_line
from .eval.stage_cache import (encoder_spec, ensure_encoder, ensure_episodes, ensure_features,
                               ensure_oracle_detections, episodes_name)
from .metrics import METRICS, write_json
from .protocol import DEFAULT_PROTOCOL, PROTOCOLS, check_protocol, protocol_line
from .pretrain.train import read_progress
from .rl.logger import read_log
from .rl.train import train_run
from .sim.episodes import read_episodes
from .world.build import BuildConfig, build_dataset
from .world.presets import preset_scenes

STAGES = ("world", "pretrain", "features", "detector", "detections", "episodes", "train", "evaluate", "report")


#: The experiment row the demo trains: TSRM + DE-MAE (paper Table II, last row).
ROW = Row("tsrm_demae", "TSRM + DE-MAE", "demae", "tsrm")


@dataclass
class DemoConfig:
    """The demo: a world preset and the ``demo`` scale of the experiments (about ten minutes of a 2-core CPU)."""

    preset: str = "demo-real"
    """World preset (``tsnav world --preset``): ``demo-real`` (28 real iTHOR rooms at 128x128) or ``demo`` (20
    procedural rooms at 64x64, with ``detector="train"``)."""
    world_workers: int = 2
    """Processes building the world."""
    train_rooms_per_type: int | None = None
    """Training rooms used per room type (the smallest ones); None: all training rooms."""
    scale: ScaleConfig = field(default_factory=lambda: SCALES["demo"])
    """Sizes of pretraining, training and evaluation (``SCALES["demo"]``: ViT-Tiny at 64x64, 300 DE-MAE steps,
    ``DEMO_UPDATES`` updates of batched A2C, 100 test episodes per room type)."""
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


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out/demo", help="folder for the world, runs and report (default out/demo)")
    p.add_argument("--workers", type=int, default=2, help="worker processes for world building")
    p.add_argument("--train-updates", type=int, default=None,
                   help=f"training budget of the agent in updates (default {DEMO_UPDATES}: the same table on any machine)")
    p.add_argument("--train-minutes", type=float, default=None,
                   help="training budget in minutes instead (the table then depends on the machine's load)")
    p.add_argument("--pretrain-steps", type=int, default=None, help="DE-MAE steps (default 300)")
    p.add_argument("--procs", type=int, default=None,
                   help="CPU processes of the agent's training (default 1; 2 uses both cores; the table is the same "
                        "on every run for a given value, but differs between values)")
    p.add_argument("--threads", type=int, default=None,
                   help=f"torch CPU threads (default {DEFAULT_THREADS}, or the machine's cores when fewer: a fixed "
                        "count, because another count sums floats in another order and trains another agent)")
    p.add_argument("--sample", action="store_true",
                   help="evaluate the agent by sampling its actions instead of the greedy argmax (the default)")
    p.add_argument("--detections", choices=("learned", "oracle"), default="learned",
                   help="learned (default): the learned detector's table (see --detector); oracle: "
                        "the oracle's table (hand-made confidence from instance size and distance)")
    p.add_argument("--preset", choices=("demo-real", "demo"), default="demo-real",
                   help="world: demo-real (default; 28 real iTHOR rooms at 128x128) or demo (20 procedural rooms "
                        "at 64x64; needs --detector train)")
    p.add_argument("--detector", choices=DETECTOR_SOURCES, default="shipped",
                   help="shipped (default): the detector that comes with tsnav, trained on the 80 ithor-real "
                        "training rooms (128-px worlds only); train: train one here on the training rooms")
    p.add_argument("--protocol", default=DEFAULT_PROTOCOL,
                   help="success protocol the agent is trained under: paper (default; in view within 1.0 m) or "
                        "lineage (the 1.5 m visibility map, as the lineage's evaluator); the results are printed "
                        "under both")
    p.add_argument("--detector-steps", type=int, default=None,
                   help=f"training steps of the learned detector with --detector train (default "
                        f"{SCALES['demo'].detector.steps})")


# ---------------------------------------------------------------------------------------------------------
# Stage bookkeeping
# ---------------------------------------------------------------------------------------------------------


class Stages:
    """Markers ``OUT/stages/<name>.json`` (seconds, summary) and the progress lines of the demo."""

    def __init__(self, out: Path):
        self.dir = out / "stages"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.times: dict[str, tuple[str, float]] = {}

    def marker(self, name: str) -> dict | None:
        p = self.dir / f"{name}.json"
        try:
            return json.loads(p.read_text()) if p.exists() else None
        except json.JSONDecodeError:
            return None

    def header(self, name: str, what: str) -> None:
        k = STAGES.index(name) + 1
        print(f"\n[{k}/{len(STAGES)}] {name}: {what}", flush=True)

    def run(self, name: str, what: str, fn, valid=lambda m: True) -> dict:
        """Run ``fn() -> summary dict`` unless a valid marker exists and no earlier stage ran in this call (the
        underlying steps skip what is already on disk, so a rerun after an upstream change is cheap)."""
        self.header(name, what)
        m = self.marker(name)
        upstream_ran = any(status == "done" for status, _ in self.times.values())
        if m is not None and not upstream_ran and valid(m):
            print(f"    reused (made by an earlier run in {m.get('seconds', 0):.0f} s)", flush=True)
            self.times[name] = ("reused", 0.0)
            return m
        t0 = time.perf_counter()
        summary = fn() or {}
        dt = time.perf_counter() - t0
        m = {**summary, "seconds": dt}
        write_json(self.dir / f"{name}.json", m)
        self.times[name] = ("done", dt)
        print(f"    done in {dt:.0f} s", flush=True)
        return m


# ---------------------------------------------------------------------------------------------------------
# Stages
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


def run_demo(out: str | Path, cfg: DemoConfig | None = None, train_fn=None) -> dict:
    """Run the demo into ``out``; returns ``{"stages": {name: (status, seconds)}, "results": {label: summary}}``.

    ``train_fn`` replaces the real trainer (tests only; see :mod:`tsnav.eval.experiment`)."""
    cfg = cfg or DemoConfig()
    check_protocol(cfg.protocol)
    if cfg.detector not in DETECTOR_SOURCES:
        raise CommandError(f"unknown detector source {cfg.detector!r} (choose from {', '.join(DETECTOR_SOURCES)})")
    if cfg.detections != "oracle" and cfg.detector == "shipped":  # refused before any work
        size, want = BuildConfig.from_preset(cfg.preset).image_size, shipped_meta()["model"]["image_size"]
        if size != want:
            raise CommandError(f"the shipped detector reads {want}x{want} frames (the ithor-real rooms), the "
                               f"{cfg.preset} world has {size}x{size}: use --detector train, or --preset demo-real")
    out = Path(out)
    index = out / "world" / "index.json"
    if index.exists():  # a world of another preset is never mixed with this one (names overlap): refused
        try:
            was = json.loads(index.read_text()).get("preset")
        except ValueError:
            was = None
        if was != cfg.preset:
            raise CommandError(f"{out / 'world'} holds the {was!r} world, not {cfg.preset!r}: use another --out "
                               f"(or --preset {was})")
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "demo_config.json", asdict(cfg))
    world = out / "world"
    sub = out / "train_world"
    st = Stages(out)
    t_all = time.perf_counter()

    # 1. world ------------------------------------------------------------------------------------------
    def do_world():
        build_dataset(world, cfg.preset, workers=cfg.world_workers)
        names = train_subset(world, sub, cfg.train_rooms_per_type)
        return {"scenes": len(list_scenes(world)), "train_rooms": names}

    def world_ok(m):
        return world.is_dir() and len(list_scenes(world)) == len(preset_scenes(cfg.preset)) and sub.is_dir()

    wm = st.run("world", f"build the `{cfg.preset}` world into {world} (finished rooms are reused)", do_world, world_ok)
    print(f"    {wm['scenes']} rooms; training on {', '.join(wm['train_rooms'])}", flush=True)

    # 2. pretrain ---------------------------------------------------------------------------------------
    sc = cfg.scale
    exp = ExperimentConfig(experiment="demo", data=str(sub), out=str(out), scale="demo", detections=cfg.detections,
                           device="cpu", protocol=cfg.protocol)
    es = encoder_spec(ROW.encoder, sc, out / "pretrain", exp)

    def do_pretrain():
        ensure_encoder(es, sub)
        prog = read_progress(es.spec)
        return {"steps": prog["step"], "loss": prog.get("loss")}

    st.run("pretrain", f"DE-MAE, {sc.pretrain.model} at {sc.pretrain.img_size}x{sc.pretrain.img_size}, {sc.pretrain.steps} steps -> {es.spec}",
           do_pretrain, lambda m: (Path(es.spec) / "encoder.safetensors").exists())

    # 3. features ---------------------------------------------------------------------------------------
    def do_features():
        name = ensure_features(es, sub, ["train"], sc.feature_batch_size, exp.device)
        ensure_features(es, world, ["test", "val"], sc.feature_batch_size, exp.device)
        return {"name": name, "scenes": sum(len(list_scenes(d, s)) for d, s in ((sub, "train"), (world, "test"),
                                                                                 (world, "val")))}

    def features_ok(m):
        rooms = list_scenes(sub, "train") + list_scenes(world, "test") + list_scenes(world, "val")
        return "name" in m and all((p / f"features_{m['name']}.hdf5").exists() for p in rooms)

    fm = st.run("features", "encode every state of the training, validation and test rooms once", do_features, features_ok)

    # 4. detector ---------------------------------------------------------------------------------------
    det_dir = out / "detector"
    learned = cfg.detections != "oracle"
    shipped = cfg.detector == "shipped"
    shipped_fp = shipped_meta()["fingerprint"]

    def do_detector():
        ready = tables_complete(world, cfg.detections)
        if ready and (ready == shipped_fp) != shipped:  # tables of the other source than the one asked for
            have = "the shipped detector's" if ready == shipped_fp else f"another learned detector's ({ready})"
            raise CommandError(f"every room of {world} holds {have} detections_{cfg.detections}.hdf5, not from "
                               f"--detector {cfg.detector}: use another --out (they are never overwritten)")
        if ready:  # every room already has a learned table (e.g. written by an experiment): used as it is
            print(f"    every room already holds detections_{cfg.detections}.hdf5 ({ready}): no detector trained",
                  flush=True)
            return {"fingerprint": ready, "tables": "existing"}
        if shipped:  # loaded (and its weights checked) by the detections stage
            meta = shipped_meta()
            print(f"    shipped detector {DEFAULT_SHIPPED}: step {meta['step']}, trained on "
                  f"{len(meta['train_scenes'])} ithor-real training rooms, temperature {meta['temperature']:.3f} "
                  f"({shipped_fp})", flush=True)
            return {"fingerprint": shipped_fp, "source": "shipped", "steps": meta["step"],
                    "temperature": meta["temperature"]}
        det = ensure_detector(sub, world, det_dir, sc, say=lambda m: print(m, flush=True))
        return {"fingerprint": det.fingerprint, "source": "train", "steps": det.meta.get("step"),
                "temperature": det.temperature}

    def detector_ok(m):
        if m.get("tables") == "existing":
            return tables_complete(world, cfg.detections) == m.get("fingerprint")
        if shipped:
            return m.get("source") == "shipped" and m.get("fingerprint") == shipped_fp
        if m.get("source", "train") != "train":  # markers written before the shipped detector have no source
            return False
        meta = read_meta(det_dir) if is_checkpoint(det_dir) else {}
        return meta.get("step") == sc.detector.steps and meta.get("calibrated_step") == sc.detector.steps

    if learned and shipped:
        st.run("detector", f"learned detector shipped with tsnav ({DEFAULT_SHIPPED}; trained on the ithor-real "
                           "training rooms apart from the agent, as the paper's DETR): nothing trained here",
               do_detector, detector_ok)
    elif learned:
        st.run("detector", f"learned detector, {sc.detector.steps} steps on the training rooms (one thread), "
                           f"temperature fitted on the val rooms -> {det_dir}", do_detector, detector_ok)
    else:
        st.header("detector", "not used (--detections oracle)")
        st.times["detector"] = ("-", 0.0)

    # 5. detections -------------------------------------------------------------------------------------
    def do_detections():
        if learned and shipped:
            done = ensure_shipped_detections(world, cfg.detections, say=lambda m: print(m, flush=True))
            fingerprint, written = done["fingerprint"], done["written"]
        elif learned:
            done = ensure_learned_detections(world, cfg.detections, det_dir, sc, train_root=sub,
                                             say=lambda m: print(m, flush=True))
            fingerprint, written = done["fingerprint"], done["written"]
        else:
            written, fingerprint = ensure_oracle_detections(world, cfg.detections), OracleConfig().fingerprint()
        quality = record_quality(out, world, [cfg.detections], say=lambda m: print(m, flush=True))
        return {"written": written, "fingerprint": fingerprint, "quality": quality[cfg.detections]}

    what = ("the learned detector's table per room" if learned else "the oracle detector's table per room")
    dm = st.run("detections", f"detections: {cfg.detections} (named explicitly), {what} (confidence drives the stage "
                         f"switch, C_target {C_TARGET:g}); quality on the val rooms", do_detections,
           lambda m: "quality" in m and all(read_fingerprint(p, cfg.detections) == m.get("fingerprint")
                                            for p in list_scenes(world)))

    # 6. episodes ---------------------------------------------------------------------------------------
    ep_files = {p: out / episodes_name("test", p) for p in PROTOCOLS}
    ep_file = ep_files[DEFAULT_PROTOCOL]
    val_file = out / episodes_name("val", cfg.protocol)

    def do_episodes():
        for p, f in ep_files.items():
            ensure_episodes(world, "test", f, sc.test_per_room_type, protocol=p)
        ensure_episodes(world, "val", val_file, sc.val_per_room_type, seed=SELECT_SEED, protocol=cfg.protocol)
        test = {p: read_episodes(f)[0] for p, f in ep_files.items()}
        return {"episodes": len(test[DEFAULT_PROTOCOL]), "val_episodes": len(read_episodes(val_file)[0]),
                "by_protocol": {p: {"episodes": len(e), "start_success": sum(x.optimal_length == 0 for x in e)}
                                for p, e in test.items()}}

    em = st.run("episodes", f"{sc.test_per_room_type} test episodes per room type under each protocol "
                f"({', '.join(PROTOCOLS)}) and {sc.val_per_room_type} validation episodes per room type ("
                f"{cfg.protocol})", do_episodes,
                lambda m: all(f.exists() for f in ep_files.values()) and val_file.exists() and "by_protocol" in m)
    for p, f in ep_files.items():
        b = em["by_protocol"][p]
        print(f"    {p}: {b['episodes']} test episodes in {f}"
              + (f" ({b['start_success']} start already succeeds)" if b["start_success"] else ""), flush=True)
    print(f"    {em['val_episodes']} in {val_file} (checkpoint selection, protocol {cfg.protocol})", flush=True)

    # 7. train ------------------------------------------------------------------------------------------
    run_dir = out / "run"

    def do_train():
        tc, agent = train_config_for(exp, sc, ROW, fm["name"], cfg.seed)
        (train_fn or train_run)(tc, agent, run_dir)
        log = read_log(run_dir)
        last = {k: log[-1][k] for k in ("update", "env_steps", "episodes", "SR") if log and k in log[-1]}
        # milestones scored greedily on the val rooms' episodes; the best is kept as run/best and evaluated
        # (resumed from run/selection.json when interrupted here)
        sel = select_checkpoint(run_dir, world, val_file, seed=cfg.seed, max_steps=sc.max_steps, c_target=ROW.c_target)
        checkpoint = chosen(sel)
        print(f"    best of {checkpoint['candidates']} checkpoints on validation: {sel['best']} (update "
              f"{checkpoint['update']}, SR {100 * checkpoint['val_SR']:.1f}, SPL {100 * checkpoint['val_SPL']:.1f})",
              flush=True)
        return {"budget": budget, "log_lines": len(log), **last, "checkpoint": checkpoint}

    budget = sc.budget
    shown = ", ".join(f"{v:g} {k}" for k, v in budget.items() if v is not None) or "1.5 M episodes"
    st.run("train", f"TSRM agent, batched A2C, {shown}, best milestone on validation -> {run_dir}", do_train,
           lambda m: m.get("budget") == budget and "checkpoint" in m and (run_dir / "config.json").exists())

    # 8. evaluate ---------------------------------------------------------------------------------------
    policies = eval_policies(cfg.detections)
    results: dict[str, dict] = {}

    def folder(name: str, protocol: str) -> Path:
        return out / "eval" / (name if protocol == DEFAULT_PROTOCOL else f"{name}_{protocol}")

    def do_eval():
        if any(det == "oracle" for _, _, det in policies):
            ensure_oracle_detections(world, "oracle")
        for p in PROTOCOLS:
            for label, name, det in policies:
                print(f"    {label} ({p}) ...", flush=True)
                results.setdefault(p, {})[label] = evaluate_to_folder(
                    folder(name, p), world, ep_files[p], policy="agent" if name.startswith("agent") else name,
                    run=run_dir if name.startswith("agent") else None, detections=det or cfg.detections,
                    seed=cfg.seed, label=label if p == DEFAULT_PROTOCOL else f"{label} [{p}]", sample=cfg.sample,
                    protocol=p)
        return {"policies": [n for _, n, _ in policies], "protocols": list(PROTOCOLS), "sample": cfg.sample}

    st.run("evaluate", "on the test episodes of each protocol: " + ", ".join(lab for lab, _, _ in policies), do_eval,
           lambda m: m.get("policies") == [n for _, n, _ in policies] and m.get("sample", True) == cfg.sample
           and m.get("protocols") == list(PROTOCOLS)
           and all((folder(n, p) / "metrics.json").exists() for _, n, _ in policies for p in PROTOCOLS))
    if not results:
        for p in PROTOCOLS:
            for label, name, _ in policies:
                results.setdefault(p, {})[label] = json.loads((folder(name, p) / "metrics.json").read_text())["metrics"]

    # 9. report -----------------------------------------------------------------------------------------
    def do_report():
        index = build_report(out, out / "report", gallery=cfg.gallery, title=f"tsnav demo: TSRM + DE-MAE on the {cfg.preset} world")
        return {"index": str(index)}

    rm = st.run("report", f"HTML report -> {out / 'report' / 'index.html'}", do_report,
                lambda m: (out / "report" / "index.html").exists())

    total = time.perf_counter() - t_all
    _print_results(results, st, total, rm.get("index", str(out / "report" / "index.html")), cfg.protocol)
    print(f"detections: {quality_line(dm['quality'])}", flush=True)
    return {"stages": st.times, "results": results, "seconds": total}


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
        lines += [f"\nresults on the test episodes (percent; paper IV-A metrics)",
                  f"{protocol_line(protocol)}; agent trained under {trained}",
                  f"{'policy':<{width}}  subset " + " ".join(f"{m:>6}" for m in METRICS) + "      K"]
        for label, s in rows.items():
            for sub in ("ALL", "L>=5"):
                m = s[sub]
                lines.append(f"{label:<{width}}  {sub:<6} " + " ".join(f"{100 * m[k]:6.2f}" for k in METRICS)
                             + f" {m['episodes']:6d}")
    return "\n".join(lines)


def _print_results(results: dict, st: Stages, total: float, index: str, trained: str = DEFAULT_PROTOCOL) -> None:
    print("\nstage        status    seconds")
    for name in STAGES:
        status, sec = st.times.get(name, ("-", 0.0))
        print(f"{name:<12} {status:<8} {sec:8.0f}")
    print(f"{'total':<12} {'':<8} {total:8.0f}")
    print(results_table(results, trained))
    print(f"\nreport: {index}")


def run(args) -> int:
    cfg = DemoConfig(preset=args.preset, detector=args.detector, world_workers=args.workers, sample=args.sample,
                     detections=args.detections, protocol=check_protocol(args.protocol))
    if args.detector_steps is not None:
        if args.detector_steps < 1:
            raise CommandError("--detector-steps must be >= 1")
        cfg.scale = cfg.scale.override(detector=dict(steps=args.detector_steps))
    if args.train_updates is not None or args.train_minutes is not None:  # asked for: replaces the default
        if args.train_updates is not None and args.train_updates < 1:
            raise CommandError("--train-updates must be >= 1")
        if args.train_minutes is not None and not args.train_minutes > 0:
            raise CommandError("--train-minutes must be positive")
        cfg.scale = cfg.scale.override(train=dict(updates=args.train_updates, minutes=args.train_minutes))
    if args.pretrain_steps is not None:
        if args.pretrain_steps < 1:
            raise CommandError("--pretrain-steps must be >= 1")
        cfg.scale = cfg.scale.override(pretrain=dict(steps=args.pretrain_steps))
    if args.threads is not None and args.threads < 1:
        raise CommandError("--threads must be >= 1")
    if args.procs is not None:
        if args.procs < 1 or cfg.scale.train.num_envs % args.procs:
            raise CommandError(f"--procs must be >= 1 and divide the {cfg.scale.train.num_envs} training episodes "
                               "per update")
        cfg.scale = cfg.scale.override(train=dict(procs=args.procs))

    print(f"tsnav demo -> {args.out} (torch threads: {set_threads(args.threads)})", flush=True)
    run_demo(args.out, cfg)
    return 0
