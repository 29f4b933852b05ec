"""The generated pages are what their generators render (run `make docs` when one of these fails), and the version,
licence and citation agree with each other."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

import tsnav
from tsnav import cli_reference
from tsnav.cli import COMMANDS
from tsnav.report import results_page
from tsnav.report.claims import PAPER_TABLE_II, published_figures

ROOT = Path(__file__).resolve().parents[2]


def test_command_reference_is_current():
    assert (ROOT / "docs" / "COMMANDS.md").read_text() == cli_reference.render(), (
        "docs/COMMANDS.md is stale: run python -m tsnav.cli_reference (or make docs)"
    )


def test_command_reference_names_every_option():
    text = cli_reference.render()
    for name in COMMANDS:
        parser = cli_reference.command_parser(name)
        assert f"## `tsnav {name}`" in text
        stack = [parser]
        while stack:
            p = stack.pop()
            for a in p._actions:
                if a.option_strings and a.help != "==SUPPRESS==":
                    assert all(f"`{o}`" in text for o in a.option_strings if o not in ("-h", "--help")), (name, a)
                if hasattr(a, "choices") and isinstance(a.choices, dict):
                    stack += list(a.choices.values())


def test_results_page_and_readme_table_are_current():
    for path, text in results_page.pages(ROOT).items():
        assert path.read_text() == text, f"{path} is stale: run python -m tsnav.report.results_page (or make docs)"


def test_results_page_reads_its_figures_from_the_files(tmp_path):
    """Figures come from the cards, the result files and paper.json: change one in a copy and the page follows;
    a RoboTHOR result named by the index replaces "not yet measured"."""
    root = tmp_path / "repo"
    shutil.copytree(ROOT / "docs" / "results", root / "docs" / "results")
    weights = tmp_path / "weights"
    shutil.copytree(results_page.WEIGHTS, weights, ignore=shutil.ignore_patterns("*.safetensors", "best"))
    card_path = weights / "tsrm-demae-learned7" / "card.json"
    card = json.loads(card_path.read_text())
    row = next(r for r in card["figures"]["test"]["rows"] if r["protocol"] == "lineage" and r["policy"] == "agent")
    row["metrics"]["ALL"]["SR"] = 0.12345
    index_path = root / "docs" / "results" / "index.json"
    index = json.loads(index_path.read_text())
    # a RoboTHOR evaluation as `tsnav release eval` writes it (results.json), named by the index
    rob = {
        "rows": [
            {
                "protocol": "lineage",
                "policy": "agent",
                "episodes": 10,
                "metrics": {
                    "ALL": {"SR": 0.5, "SPL": 0.25, "SSR": 0.6, "SSSPL": 0.3, "NSNPL": 0.45},
                    "L>=5": {"SR": 0.4, "SPL": 0.2, "SSR": 0.5, "SSSPL": 0.25, "NSNPL": 0.4},
                },
            }
        ]
    }
    (root / "docs" / "results" / "robothor_test.json").write_text(json.dumps(rob))
    index["table1"]["robothor"] = {"tsrm-demae-learned7": "robothor_test.json"}
    index_path.write_text(json.dumps(index))
    card_path.write_text(json.dumps(card))
    text = results_page.render(root, weights)
    line = next(l for l in text.splitlines() if l.startswith("| **tsnav `tsrm-demae-learned7`**"))
    assert "| 12.35 / 41.72 |" in line and "| 50.00 / 25.00 | 40.00 / 20.00 |" in line
    assert "not yet measured" in text  # the other rows
    # the paper's figures: from paper.json, once
    assert "| **TSRM + DE-MAE (the paper)** | published (paper's Table I) | 86.73 / 50.48 | 81.71 / 52.09 |" in text
    assert PAPER_TABLE_II["tsrm_demae"]["ALL"]["SR"] == published_figures()["table2"]["rows"]["tsrm_demae"]["ALL"][0]
    # Table II: the paper's value beside tsnav's mean and interval, from the result file
    res = json.loads((root / "docs" / "results" / index["table2"][0]["file"]).read_text())
    base = next(r for r in res["rows"] if r["row"] == "baseline")["metrics"]["ALL"]["SR"]
    assert f"| baseline (ResNet18, baseline reward) | 81.92 | {base['mean']:.2f} ± {base['ci95']:.2f} |" in text
    # the lever tables: every row of every protocol, its value and interval from its file
    look = index["table1"].get("robothor_inferred_look")
    if look:  # the inferred-look rows, from their file
        for r in json.loads((root / "docs" / "results" / look).read_text())["rows"]:
            assert f"| {r['policy']} | {r['episodes']} | {100 * r['metrics']['ALL']['SR']:.2f} |" in text
    if index.get("robothor_levers"):
        assert "### RoboTHOR: levers on the column" in text
    for e in index.get("levers", []) + index.get("robothor_levers", []):
        assert not e.get("title") or f"#### {e['title']}\n" in text
    for e in index.get("levers", []) + index.get("robothor_levers", []):
        lev = json.loads((root / "docs" / "results" / e["file"]).read_text())
        for t in lev["protocols"].values():
            for r in t["rows"]:
                lo, hi = (100 * q for q in r["ALL"]["SR"]["ci95"])
                assert f"| {r['row']} | {100 * r['ALL']['SR']['value']:.2f} [{lo:.2f}, {hi:.2f}] |" in text
    # the README block is replaced, not duplicated, and a README without one is refused in one line
    readme = f"a\n{results_page.README_BEGIN}\nold\n{results_page.README_END}\nb\n"
    new = results_page.with_readme_table(readme, "T")
    assert new == f"a\n{results_page.README_BEGIN}\nT\n{results_page.README_END}\nb\n"
    with pytest.raises(ValueError, match="no Table I block"):
        results_page.with_readme_table("a\n", "T")


def test_the_pages_have_no_figure_typed_twice_in_the_readme():
    """Every SR / SPL pair in README.md sits inside the rendered Table I block."""
    readme = (ROOT / "README.md").read_text()
    outside = readme.split(results_page.README_BEGIN)[0] + readme.split(results_page.README_END)[1]
    assert not re.findall(r"\b\d{2}\.\d{2} / \d{2}\.\d{2}\b", outside)


def test_version_licence_and_citation_agree():
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'dynamic = ["version"]' in pyproject and 'version = {attr = "tsnav.__version__"}' in pyproject
    assert re.search(r'^license = "Apache-2.0"$', pyproject, re.M)
    assert "Apache License" in (ROOT / "LICENSE").read_text().splitlines()[1]
    cff = (ROOT / "CITATION.cff").read_text()
    assert re.search(rf'^version: "{re.escape(tsnav.__version__)}"$', cff, re.M) and "license: Apache-2.0" in cff
    assert f"## {tsnav.__version__}" in (ROOT / "CHANGELOG.md").read_text()
    notice = (ROOT / "NOTICE").read_text()
    assert "ithor_layouts.json.gz" in notice and "MIT License" in notice and "Apache License" in notice
    readme = (ROOT / "README.md").read_text()
    assert "@misc{" in readme and "Yanwei Zheng" in readme and len(readme.splitlines()) <= 150


USER_PAGES = [
    "README.md",
    "docs/getting-started.md",
    "docs/concepts.md",
    "docs/RESULTS.md",
    *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs" / "howto").glob("*.md")),
]


def doc_commands(text: str) -> list[str]:
    """Every ``tsnav ...`` command line of the page's code blocks (continuations joined, comments dropped)."""
    out = []
    for lang, body in re.findall(r"^```(\w*)[^\n]*\n(.*?)^```", text, re.S | re.M):
        if lang in ("python", "json", "bibtex", "text"):  # text: diagrams
            continue
        for line in body.replace("\\\n", " ").splitlines():
            line = line.split(" #")[0].strip()
            if line.startswith("tsnav "):
                out.append(line)
    return out


@pytest.mark.parametrize("page", USER_PAGES)
def test_every_command_of_the_user_pages_parses(page):
    """The commands a user copies from these pages are accepted by today's parsers (options renamed or removed
    fail here)."""
    import shlex

    text = (ROOT / page).read_text()
    settings = dict(re.findall(r"^([A-Z_][A-Z0-9_]*)=(\S+)", text, re.M))  # a how-to's scale settings
    commands = doc_commands(text)
    assert commands
    for line in commands:
        argv = shlex.split(re.sub(r"\$\{?(\w+)\}?", lambda m: settings.get(m.group(1), "X"), line))
        assert argv[1] in COMMANDS, f"{page}: unknown command in `{line}`"
        parser = cli_reference.command_parser(argv[1])
        try:
            parser.parse_args(argv[2:])
        except SystemExit:
            pytest.fail(f"{page}: `{line}` does not parse")


@pytest.mark.parametrize("page", [*USER_PAGES, "docs/COMMANDS.md", "BENCHMARKS.md", "CHANGELOG.md"])
def test_links_of_the_user_pages_resolve(page):
    """Every relative link of the page names a file or folder of the checkout."""
    path = ROOT / page
    for target in re.findall(r"\]\(([^)\s]+)\)", path.read_text()):
        if target.startswith(("http://", "https://", "#", "mailto:")):
            continue
        assert (path.parent / target.split("#")[0]).exists(), f"{page}: broken link {target}"


def test_fig4_section_reads_its_rows_and_the_threshold_claim(tmp_path):
    """A threshold experiment named by the index: its rows in C_target order, each metric's best mean in bold, its
    picture, and the paper's claim (0.7 best) read by tsnav.report.claims from the same file."""
    from tsnav.report.tables import aggregate
    from tsnav.pipeline.config import Row

    rows = [Row(f"c{c}", f"C_target = 0.{c // 10}", "demae", "tsrm", c / 100) for c in (70, 10, 90)]
    sr = {"c10": [40.0, 42.0], "c70": [80.0, 81.0], "c90": [60.0, 62.0]}
    spl = {"c10": [30.0, 31.0], "c70": [35.0, 36.0], "c90": [39.0, 41.0]}
    per_row = {
        rid: [
            {
                s: {m: v / 100 for m, v in zip(("SR", "SPL", "SSR", "SSSPL", "NSNPL"), (a, b, 50, 50, 50))}
                for s in ("ALL", "L>=5")
            }
            for a, b in zip(sr[rid], spl[rid])
        ]
        for rid in sr
    }
    res = aggregate(rows, per_row, ["SR", "SPL", "SSR", "SSSPL", "NSNPL"], []) | {"protocol": "lineage"}
    (tmp_path / "fig4.json").write_text(json.dumps(res))
    entry = {"file": "fig4.json", "setting": "a test", "command": "tsnav experiment threshold", "picture": "img/f.png"}
    text = "\n".join(results_page.fig4({"fig4": [entry]}, tmp_path))
    body = [line for line in text.splitlines() if line.startswith("| 0.")]
    assert [line.split(" |")[0] for line in body] == ["| 0.1", "| 0.7", "| 0.9"]
    assert "| 0.7 | **80.50 ±" in text and "| 0.9 | 61.00 ±" in text and "| **40.00 ±" in text
    assert "![Fig. 4 at this setting" in text and "(img/f.png)" in text
    assert "under `lineage`" in text and "2 seeds per threshold" in text
    sr_line = next(line for line in text.splitlines() if line.startswith("- SR:"))
    spl_line = next(line for line in text.splitlines() if line.startswith("- SPL:"))
    assert "(C_target = 0.9): +19.50" in sr_line and "supported" in sr_line
    assert "(C_target = 0.9): -4.50" in spl_line and "n.s." in spl_line


def test_robothor_switch_reach_section_reads_its_file():
    """Every switch row and every cell row of the switch-reach file named by the index shows on the page."""
    index = json.loads((ROOT / "docs" / "results" / "index.json").read_text())
    entry = index["table1"].get("robothor_switch_reach")
    if not entry:
        pytest.skip("the index names no switch-reach file")
    res = json.loads((ROOT / "docs" / "results" / entry["file"]).read_text())
    text = "\n".join(results_page.robothor_switch_reach(index, ROOT / "docs" / "results"))
    for r in res["rows"]:
        assert f"| {r['switch']} | {r['episodes']} | {100 * r['metrics']['ALL']['SR']:.2f} |" in text
    for c in res["cells"]:
        assert f"| {c['threshold']:g} | {100 * c['precision']:.2f} | {100 * c['recall']:.2f} |" in text


def test_switch_distance_section_reads_its_file():
    """Every evaluation of the switch-distance file shows on the page with each band's share and the far losses."""
    index = json.loads((ROOT / "docs" / "results" / "index.json").read_text())
    entry = index.get("switch_distance")
    if not entry:
        pytest.skip("the index names no switch-distance file")
    res = json.loads((ROOT / "docs" / "results" / entry["file"]).read_text())
    text = "\n".join(results_page.switch_distance(index, ROOT / "docs" / "results"))
    for ev in res["evaluations"]:
        row = next(line for line in text.splitlines() if line.startswith(f"| {ev['label']} | {ev['episodes']} |"))
        for b in ev["bands"]:
            assert f"{100 * b['success_share']:.2f} ({b['episodes']})" in row
        lost = sum(b["episodes"] - b["successes"] for b in ev["bands"] if b["from"] >= entry.get("far_from", 15))
        assert row.endswith(f"| {lost} ({100 * lost / ev['episodes']:.2f}) |")
        assert sum(b["episodes"] for b in ev["bands"]) == ev["switched"]
        if "false_switches" in ev["bands"][0]:
            n, won = (sum(b[k] for b in ev["bands"]) for k in ("false_switches", "false_successes"))
            assert any(
                line.startswith(f"| {ev['label']} |") and line.endswith(f"| {n} ({won}) |")
                for line in text.splitlines()
            )
