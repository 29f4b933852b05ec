"""The extension how-tos (docs/howto/add-a-reward-term.md, add-an-encoder.md, add-a-metric.md), run as a user
follows them: every ```` ```python ```` block of a page, in order, in one namespace, in a temporary folder, on the
test suite's tiny world (the world the page's bash block builds). A setting line ``NAME = value  # ... (test: ...)``
is the page's scale: the test replaces its value and nothing else. The registrations a page makes are undone after
it, so the rest of the suite sees the built-in terms, encoders and metrics."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

from conftest import PIXEL_FEATURES

ROOT = Path(__file__).resolve().parents[2]
HOWTO = ROOT / "docs" / "howto"
BLOCK = re.compile(r"^```python[^\n]*\n(.*?)^```", re.S | re.M)

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]  # the tiny world, training


def page_code(page: Path, overrides: dict[str, str]) -> str:
    """The page's Python blocks joined, with each overridden setting's value replaced (each must exist)."""
    code = "\n".join(BLOCK.findall(page.read_text()))
    for name, value in overrides.items():
        code, n = re.subn(
            rf"^{name} = [^#\n]*(#.*\(test: .*\))$", lambda m: f"{name} = {value}  {m.group(1)}", code, flags=re.M
        )
        assert n == 1, f"{page.name}: no setting {name} marked (test: ...)"
    return code


@pytest.fixture
def registries():
    """Snapshot of every registry a how-to extends, restored afterwards."""
    from tsnav import metrics
    from tsnav.pretrain import archs, encoders
    from tsnav.tsrm import terms

    saved = [
        (d, dict(d))
        for d in (
            terms.TERM_CLASSES,
            terms.VARIANT_TERMS,
            metrics.METRIC_REGISTRY,
            encoders.ENCODERS,
            archs.ENCODER_ARCHS,
        )
    ]
    yield
    for d, old in saved:
        d.clear()
        d.update(old)


def run_page(name: str, overrides: dict[str, str], cwd: Path) -> dict:
    old = Path.cwd()
    os.chdir(cwd)
    try:
        ns = {"__name__": "__howto__"}
        exec(compile(page_code(HOWTO / name, overrides), name, "exec"), ns)
        return ns
    finally:
        os.chdir(old)


def test_add_a_reward_term(pixel_world, tmp_path, registries, capsys):
    from tsnav.tsrm.reward import TERMS, VARIANTS

    ns = run_page(
        "add-a-reward-term.md",
        {"WORLD": repr(str(pixel_world)), "FEATURES": repr(PIXEL_FEATURES), "UPDATES": "2"},
        tmp_path,
    )
    out = capsys.readouterr().out
    assert "revisit" in TERMS and "tsrm-revisit" in VARIANTS
    assert ns["charged"] > 0 and "batched, scalar and reference agree" in out
    assert ns["progress"]["update"] == 2
    log = (tmp_path / "work" / "run-revisit" / "log.jsonl").read_text()
    assert '"reward/revisit"' in log


def test_add_an_encoder(pixel_world, tmp_path, registries, capsys):
    ns = run_page(
        "add-an-encoder.md", {"WORLD": repr(str(pixel_world)), "IMG": "32", "STEPS": "2", "UPDATES": "2"}, tmp_path
    )
    enc = ns["encoder"]
    assert enc.arch == "tinycnn" and enc.method == "tinycnn-sup" and enc.img_size == 32
    assert ns["progress"]["update"] == 2
    assert all(
        (p / f"features_{ns['name']}.hdf5").exists() for p in Path(pixel_world).iterdir() if (p / "COMPLETE").exists()
    )


def test_add_a_metric(pixel_world, tmp_path, registries, capsys):
    from tsnav.cli import main
    from tsnav.metrics import METRICS, curve_metrics
    from tsnav.rl.logger import tag_group

    # the page's `tsnav episodes` line, with 4 episodes per room type
    (tmp_path / "work").mkdir()
    assert (
        main(
            [
                "episodes",
                "--data",
                str(pixel_world),
                "--split",
                "val",
                "--per-room-type",
                "4",
                "--out",
                str(tmp_path / "work" / "val_episodes.json"),
            ]
        )
        == 0
    )
    ns = run_page(
        "add-a-metric.md", {"WORLD": repr(str(pixel_world)), "FEATURES": repr(PIXEL_FEATURES), "UPDATES": "2"}, tmp_path
    )
    out = capsys.readouterr().out
    assert "NSR" in METRICS and "NSR" in curve_metrics() and tag_group("NSR") == "metrics"
    summary = ns["summary"]
    k_nav = summary["ALL"]["K_nav"]
    assert 0 <= summary["ALL"]["NSR"] <= 1 and (k_nav > 0 or summary["ALL"]["NSR"] == 0)
    assert "NSR" in out.splitlines()[[i for i, line in enumerate(out.splitlines()) if "subset" in line][0]]
    assert '"NSR"' in (tmp_path / "work" / "run-nsr" / "log.jsonl").read_text()
