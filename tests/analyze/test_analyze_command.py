"""``tsnav analyze``: the analyses behind docs/RESULTS.md, one subcommand each; every one that RESULTS names is in
the table, and each builds its parser under ``tsnav analyze NAME``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tsnav.analyze.command import ANALYSES
from tsnav.cli import main

ROOT = Path(__file__).resolve().parents[2]


def test_lists_the_analyses(capsys):
    assert main(["analyze"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in ANALYSES)


def test_every_analysis_the_docs_name_exists():
    named = set()
    for page in [ROOT / "BENCHMARKS.md", ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        named |= set(re.findall(r"tsnav analyze ([a-z-]+)", page.read_text()))
    assert named and named <= set(ANALYSES)
    assert not list((ROOT / "scripts").glob("*.py"))  # no analysis left outside the package


@pytest.mark.parametrize("name", list(ANALYSES))
def test_each_analysis_parses_its_options(name, capsys):
    with pytest.raises(SystemExit) as e:
        main(["analyze", name, "--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: tsnav analyze {name}")


def test_unknown_analysis_is_refused(capsys):
    with pytest.raises(SystemExit) as e:
        main(["analyze", "nope"])
    assert e.value.code == 2 and "invalid choice: 'nope'" in capsys.readouterr().err
