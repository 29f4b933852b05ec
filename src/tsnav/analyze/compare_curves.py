"""Validation curves of several `tsnav convergence` folders in one picture, with reference lines.

    tsnav analyze compare-curves --out docs/convergence_real_rooms.png \\
        --curve "lr 1e-4=CONV_A" --curve "lr 1e-3=CONV_B" --ref "scripted explorer, learned switch=36.5"

Each ``--curve LABEL=FOLDER`` reads FOLDER/curve.json (written by `tsnav convergence`); each ``--ref LABEL=VALUE``
draws a dashed horizontal line (percent) on the SR panel. Panels: validation SR, SPL and NSNPL against
environment steps.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ..atomic import atomic_save_figure


def split_pair(text: str, what: str) -> tuple[str, str]:
    if "=" not in text:
        raise SystemExit(f"{what} {text!r}: expected LABEL=VALUE")
    label, value = text.rsplit("=", 1)
    return label, value


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        allow_abbrev=False, prog="tsnav analyze compare-curves", description=__doc__.splitlines()[0]
    )
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--curve", action="append", default=[], help="LABEL=FOLDER of a `tsnav convergence` run")
    p.add_argument("--ref", action="append", default=[], help="LABEL=PERCENT: a reference SR line")
    p.add_argument("--title", default="")
    a = p.parse_args(argv)
    curves = []
    for c in a.curve:
        label, folder = split_pair(c, "--curve")
        f = Path(folder) / "curve.json"
        try:
            pts = json.loads(f.read_text())["points"]
        except (OSError, ValueError, KeyError) as e:
            raise SystemExit(f"{f}: no readable convergence curve ({e})")
        curves.append((label, pts))
    fig = Figure(figsize=(15, 4.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    for ax, metric in zip(axes, ("SR", "SPL", "NSNPL")):
        for label, pts in curves:
            ax.plot([q["env_steps"] / 1e6 for q in pts], [100 * q[metric] for q in pts], marker="o", ms=3, label=label)
        if metric == "SR":
            for r in a.ref:
                label, value = split_pair(r, "--ref")
                ax.axhline(float(value), ls="--", lw=1, color="grey")
                ax.text(0.01, float(value) + 1, label, transform=ax.get_yaxis_transform(), fontsize=7, color="dimgrey")
        ax.set_xlabel("environment steps (millions)")
        ax.set_ylabel(f"validation {metric}, %")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=8, loc="upper left")  # SPL stays low: its upper half is free
    if a.title:
        fig.suptitle(a.title)
    fig.tight_layout()
    atomic_save_figure(fig, a.out, dpi=100)
    print(f"wrote {a.out}")
    return 0
