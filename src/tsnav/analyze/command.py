"""``tsnav analyze NAME [options]``: the analyses that docs/RESULTS.md cites, one module each.

    tsnav analyze                      # the list
    tsnav analyze NAME --help          # one analysis's options

Each module exposes ``main(argv) -> int`` with its own options; it is imported only when it runs.
"""

from __future__ import annotations

import argparse
import importlib

#: analysis -> (module under tsnav.analyze, one-line help)
ANALYSES = {
    "agent-diagnostics": ("agent_diagnostics", "evaluation folders: rotations, reachable targets, outcomes, switches"),
    "class-calibration": ("class_calibration", "per-class Platt calibration of a learned detector's tables"),
    "collect-runs": ("collect_runs", "convergence runs and their test evaluations into one results JSON"),
    "compare-curves": ("compare_curves", "validation curves of several convergence folders in one picture"),
    "demo-factor": ("demo_factor", "one factor at the demo's scale, trained over seeds and tabulated"),
    "depth-readout": (
        "depth_readout",
        "a depth decoder on a frozen encoder's feature map (an input the agent may read)",
    ),
    "detector-tta": ("detector_tta", "flip test-time augmentation of a shipped detector on a split's rooms"),
    "detector-zoom": ("detector_zoom", "zoomed crops at test time for a shipped detector's small objects"),
    "done-collapse": ("done_collapse", "which reward term makes the agent stop taking Done"),
    "false-boxes": ("false_boxes", "what lies under a detector's boxes on targets that are not in view"),
    "lever-table": ("lever_table", "levers against a base run on the same episodes, paired bootstrap intervals"),
    "merge-rows": ("merge_rows", "complete an experiment's table with rows of another experiment"),
    "noisy-tables": ("noisy_tables", "tables of the shipped detector on frames with Gaussian pixel noise"),
    "pathfinding-steps": ("pathfinding_steps", "what each action after the switch did to the distance to the target"),
    "plot-selection": ("plot_selection", "a run's milestones scored on one or two episode lists"),
    "policy-ensemble": ("policy_ensemble", "evaluate an ensemble of trained agents"),
    "recall-by-size": ("recall_by_size", "tables' recall at C_target by the target's pixels in view, per class"),
    "stop-signal": ("stop_signal", "can the agent's inputs tell a success state from a near miss"),
    "stop-head": ("stop_head", "a stop head trained on the agent's inputs: would it stop sooner than the agent"),
    "stop-ceiling": ("stop_ceiling", "an evaluation's SR and SPL with Done at the first success state it reaches"),
    "switch-reach": ("switch_reach", "the explorer on switches of known reach: how soon must the target be recognised"),
    "table-ablation": ("table_ablation", "detection tables that mend one kind of a learned detector's error"),
    "wrong-done": ("wrong_done", "where an evaluation's failed Dones happen"),
}


def build_parser(p: argparse.ArgumentParser) -> None:
    p.description = "analyses behind docs/RESULTS.md: " + "; ".join(ANALYSES)
    p.add_argument(
        "analysis", nargs="?", choices=sorted(ANALYSES), metavar="NAME", help="one of: " + ", ".join(ANALYSES)
    )
    p.add_argument("options", nargs=argparse.REMAINDER, help="the analysis's own options (NAME --help)")


def run(args: argparse.Namespace) -> int:
    if args.analysis is None:
        width = max(map(len, ANALYSES))
        print("tsnav analyze NAME [options]  (NAME --help for its options)\n")
        for name, (_, help_) in ANALYSES.items():
            print(f"  {name:<{width}}  {help_}")
        return 0
    module = importlib.import_module(f"{__package__}.{ANALYSES[args.analysis][0]}")
    return int(module.main(args.options) or 0)
