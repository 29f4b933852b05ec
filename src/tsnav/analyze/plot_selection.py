"""Plot how a run's milestones score on one or two episode lists: the ``selection.json`` of ``tsnav select`` (or of a
``tsnav convergence`` run) for the training's own episodes beside one written by ``tsnav select`` on another list.

Each ``--run LABEL=SMALL,LARGE`` names two selection files of one run (the same milestones scored on two episode
lists), or ``--run LABEL=SELECTION`` one; the figure has SR and SPL per update, one colour per run, dashed for SMALL
and solid for LARGE (or the one), the chosen milestone of each ringed. The number of episodes of each list is read from the files.

    tsnav analyze plot-selection --out docs/X.png --title "..." \\
        --run "seed 3=RUN/selection.json,RUN2K/selection.json" --run "seed 2=..."
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import CommandError, read_json


def read_selection(path: str) -> tuple[list[int], list[float], list[float], int, int]:
    """(updates, SR %, SPL %, update of the chosen milestone, episodes) of one ``selection.json``."""
    doc = read_json(Path(path), CommandError, missing="no such file")
    try:
        scores = doc["scores"]
        rows = sorted(
            (
                int(v["update"]),
                100 * v["metrics"]["ALL"]["SR"],
                100 * v["metrics"]["ALL"]["SPL"],
                int(v["metrics"]["ALL"]["episodes"]),
            )
            for v in scores.values()
        )
        best = doc["best"]
    except (KeyError, TypeError, ValueError) as e:
        raise CommandError(f"{path}: not a selection.json of tsnav select ({e})") from None
    if not rows:
        raise CommandError(f"{path}: no scored milestone")
    if best not in scores:
        raise CommandError(
            f"{path}: its chosen milestone {best!r} is not among its scored ones (a selection still running?)"
        )
    return ([r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], int(scores[best]["update"]), rows[0][3])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze plot-selection", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--out", required=True, help="PNG to write")
    ap.add_argument("--title", default="milestones scored on validation episodes")
    ap.add_argument(
        "--run",
        action="append",
        required=True,
        metavar="LABEL=SEL[,LARGE]",
        help="a run's selection.json files: two (the same milestones on a small and a large list) or one",
    )
    ap.add_argument("--episodes", default="val", help="what the scored episodes are, for the labels (default val)")
    args = ap.parse_args(argv)
    try:
        runs = []
        for text in args.run:
            label, sep, files = text.partition("=")
            parts = files.split(",")
            if not sep or not label or len(parts) not in (1, 2) or not all(parts):
                raise CommandError(
                    f"--run {text!r}: expected LABEL=SELECTION.json or LABEL=SMALL_SELECTION.json,LARGE_SELECTION.json"
                )
            sels = [read_selection(f) for f in parts]
            runs.append((label, sels[0] if len(sels) == 2 else None, sels[-1]))
    except CommandError as e:
        print(f"plot_selection: error: {e}", file=sys.stderr)
        return 2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for i, (label, small, large) in enumerate(runs):
        colour = f"C{i}"
        for sel, style in ((small, "--"), (large, "-")):
            if sel is None:
                continue
            updates, sr, spl, best, n = sel
            for ax, ys in zip(axes, (sr, spl)):
                ax.plot(updates, ys, style, color=colour, marker=".", label=f"{label}, {n} {args.episodes} episodes")
                b = updates.index(best)
                ax.plot([updates[b]], [ys[b]], "o", ms=11, mfc="none", mec=colour)
    for ax, name in zip(axes, ("SR", "SPL")):
        ax.set_xlabel("update")
        ax.set_ylabel(f"{name} on the {args.episodes} episodes, %")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="lower right")
    fig.suptitle(args.title + " (ringed: the milestone each set chooses)")
    fig.tight_layout()
    out = Path(args.out)
    tmp = out.with_name(out.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    tmp.replace(out)
    print(f"wrote {out}")
    return 0
