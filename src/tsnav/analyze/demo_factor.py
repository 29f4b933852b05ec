"""One factor of issue 23 at the demo's scale: the demo's agent (TSRM + DE-MAE, 28 real rooms, 1000 updates) with
one setting changed, over several seeds, against the demo itself over the same seeds.

    tsnav analyze demo-factor BASE VARIANT SEED [SEED ...]
    tsnav analyze demo-factor BASE --table VARIANT [VARIANT ...]

VARIANT is one of :data:`VARIANTS` (``p16-64``: the demo as it is, a 4x4 token grid; ``p16-128``: the same ViT-Tiny
on the world's own 128-px frames, an 8x8 grid). Each (variant, seed) is a demo folder ``BASE/VARIANT-sSEED``; the
first folder made (``BASE/p16-64-s0``, i.e. ``tsnav demo --preset demo-real``) owns the world, the others link to it,
and the
seeds of one variant share its pretraining (``BASE/pretrain-VARIANT``), as the experiments' seeds do. Every step
resumes. ``--table`` prints the per-seed figures of both protocols and each variant's mean with its 95 % t-interval,
and writes them to ``BASE/factor.json``; it also evaluates each finished agent by sampling its actions (3 rolls
of the paper test episodes, ``OUT/eval_sampled``) beside the demo's greedy figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..eval.runner import evaluate_to_folder
from ..metrics import write_json
from ..pipeline.config import SCALES
from ..pipeline.demo import DemoConfig, run_demo
from ..distributed import set_threads
from ..protocol import PROTOCOLS
from ..report.tables import mean_ci

#: Variant name -> fields of the demo scale's configurations changed (:meth:`ScaleConfig.override`): the demo as it
#: is; the encoder on the world's own 128-px frames (an 8x8 token grid instead of 4x4); patch 8 at 64 px (8x8 as
#: well); training episodes of 100 actions (the test length) instead of the lineage's 30.
VARIANTS = {
    "p16-64": {},
    "p16-128": {"pretrain": {"img_size": 128}},
    "p8-64": {"pretrain": {"patch_size": 8}},
    "ep100": {"train": {"max_steps": 100}},
    "lin": {"protocol": "lineage"},
    "lin-ep100": {"protocol": "lineage", "train": {"max_steps": 100}},
}
#: Variants whose encoder is the demo's own (they share its pretraining and features).
SAME_ENCODER = ("p16-64", "ep100", "lin", "lin-ep100")
OWNER = "p16-64-s0"


def columns_ci(vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column of ``vals`` ``(seeds, metrics)``: the mean and the half-width of its 95 % t-interval
    (:func:`tsnav.report.tables.mean_ci`; 0 with one seed)."""
    cols = [mean_ci(vals[:, j]) for j in range(vals.shape[1])]
    return np.array([m for m, _ in cols]), np.array([h or 0.0 for _, h in cols])


def folder(base: Path, variant: str, seed: int) -> Path:
    return base / f"{variant}-s{seed}"


def prepare(base: Path, variant: str, seed: int) -> Path:
    """The run folder, linked to the owner's world and the variant's shared pretraining."""
    out = folder(base, variant, seed)
    if out.name == OWNER:
        return out
    owner = base / OWNER
    if not (owner / "steps" / "world" / "DONE").exists():
        raise SystemExit(f"run {owner} first (it builds the world the other folders share)")
    out.mkdir(parents=True, exist_ok=True)
    if not (out / "world").exists():
        (out / "world").symlink_to((owner / "world").resolve(), target_is_directory=True)
    shared = base / f"pretrain-{variant}"
    if variant in SAME_ENCODER:
        shared = owner / "pretrain"
    shared.mkdir(parents=True, exist_ok=True)
    if not (out / "pretrain").exists():
        (out / "pretrain").symlink_to(shared.resolve(), target_is_directory=True)
    return out


def run(base: Path, variant: str, seeds: list[int], threads: int | None = None) -> None:
    if variant not in VARIANTS:
        raise SystemExit(f"unknown variant {variant!r} (choose from {', '.join(VARIANTS)})")
    spec = dict(VARIANTS[variant])
    protocol = spec.pop("protocol", "paper")
    print(f"torch threads: {set_threads(threads)}", flush=True)
    for seed in seeds:
        out = prepare(base, variant, seed)
        scale = SCALES["demo"].override(**spec)
        print(f"=== {out}", flush=True)
        run_demo(out, DemoConfig(preset="demo-real", scale=scale, seed=seed, protocol=protocol))


def sampled(out: Path, rolls: int = 3) -> list[tuple[float, float]]:
    """The agent of a finished run folder evaluated by sampling its actions (seeds 0 .. rolls-1) on the paper
    test episodes, written to ``OUT/eval_sampled/sSEED`` (made when missing): ``[(SR, SPL), ...]`` in percent."""
    figs = []
    for k in range(rolls):
        f = out / "eval_sampled" / f"s{k}"
        if not (f / "metrics.json").exists():
            evaluate_to_folder(
                f,
                out / "world",
                out / "test_episodes.json",
                policy="agent",
                run=out / "run",
                detections="learned",
                seed=k,
                sample=True,
                protocol="paper",
            )
        m = json.loads((f / "metrics.json").read_text())["metrics"]["ALL"]
        figs.append((100 * m["SR"], 100 * m["SPL"]))
    return figs


def table(base: Path, variants: list[str]) -> None:
    rows, report, outcomes = [], {}, {}
    for variant in variants:
        per_seed = {}
        for d in sorted(p for p in base.glob(f"{variant}-s*") if p.is_dir()):
            seed = int(d.name.rsplit("-s", 1)[1])
            figs = {}
            for p in PROTOCOLS:
                for name in ("agent", "agent_oracle"):
                    f = d / "eval" / (name if p == "paper" else f"{name}_{p}") / "metrics.json"
                    if f.exists():
                        m = json.loads(f.read_text())["metrics"]["ALL"]
                        figs[f"{name}/{p}"] = (100 * m["SR"], 100 * m["SPL"])
                        o = f.parent / "outcomes.json"
                        if o.exists() and name == "agent" and p == "paper":
                            outcomes[(variant, seed)] = json.loads(o.read_text())
            if figs:
                if (d / "eval" / "agent" / "metrics.json").exists():
                    figs["agent sampled x3/paper"] = tuple(np.mean(sampled(d), axis=0))
                per_seed[seed] = figs
        report[variant] = {str(s): {k: list(v) for k, v in f.items()} for s, f in per_seed.items()}
        keys = sorted({k for f in per_seed.values() for k in f})
        for k in keys:
            vals = np.array([f[k] for f in per_seed.values() if k in f])
            n = len(vals)
            mean, half = columns_ci(vals)
            rows.append((variant, k, n, " ".join(f"{a:.2f}/{b:.2f}" for a, b in vals), mean, half))
    print("| variant | policy / protocol | seeds | per seed SR/SPL | mean SR +- 95% | mean SPL +- 95% |")
    print("| --- | --- | ---: | --- | --- | --- |")
    for v, k, n, per, mean, half in rows:
        print(f"| {v} | {k} | {n} | {per} | {mean[0]:.2f} +- {half[0]:.2f} | {mean[1]:.2f} +- {half[1]:.2f} |")
    ref = variants[0]
    print(
        f"\n| variant | policy / protocol | paired difference against {ref} per seed (SR) | mean SR +- 95% "
        "| mean SPL +- 95% |"
    )
    print("| --- | --- | --- | --- | --- |")
    for v in variants[1:]:
        for k in sorted({k for f in report[v].values() for k in f}):
            pairs = [
                (np.array(report[v][s][k]), np.array(report[ref][s][k]))
                for s in report[v]
                if s in report[ref] and k in report[ref][s]
            ]
            if len(pairs) < 2:
                continue
            d = np.array([a - b for a, b in pairs])
            _, half = columns_ci(d)
            print(
                f"| {v} | {k} | {' '.join(f'{x:+.2f}' for x in d[:, 0])} | {d[:, 0].mean():+.2f} +- {half[0]:.2f} | "
                f"{d[:, 1].mean():+.2f} +- {half[1]:.2f} |"
            )
    print(
        "\n| variant | seed | switched | success after the switch | step limit after the switch | passed a success "
        "state without Done | never switched, step limit | RotateLeft / RotateRight / MoveAhead share |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |")
    for (v, seed), o in sorted(outcomes.items()):
        a, c, sh = o["after_switch"], o["counts"], o["action_shares"]
        print(
            f"| {v} | {seed} | {o['switched']} | {a['success']} | {c.get('step limit, switched', 0)} | "
            f"{a['failures'].get('passed a success state without Done', 0)} | "
            f"{c.get('step limit, never switched', 0)} | "
            f"{sh['RotateLeft']:.2f} / {sh['RotateRight']:.2f} / {sh['MoveAhead']:.2f} |"
        )
        report[v][str(seed)]["outcomes_paper"] = {
            k: o[k] for k in ("switched", "counts", "after_switch", "action_shares")
        }
    write_json(base / "factor.json", report)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze demo-factor", description=__doc__.splitlines()[0]
    )
    p.add_argument("base", type=Path)
    p.add_argument("variant", nargs="?")
    p.add_argument("seeds", nargs="*", type=int)
    p.add_argument("--table", nargs="+", metavar="VARIANT")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads of the runs (default: the demo's 2; another count trains other agents, so "
        "compare only runs made with the same count)",
    )
    a = p.parse_args(argv)
    if a.table:
        table(a.base, a.table)
    else:
        run(a.base, a.variant, a.seeds or [0], a.threads)
    return 0
