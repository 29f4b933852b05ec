"""The paper's claims read against experiment results: differences, Welch p-values, verdicts, the table and
the ``tsnav claims`` command."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.stats import t as student

from tsnav.cli import main
from tsnav.report.claims import (
    CLAIMS,
    PAPER_TABLE_II,
    check_claims,
    claims_html,
    claims_markdown,
    summary_line,
    verdict,
)
from tsnav.pipeline.config import experiment_rows
from tsnav.report.tables import aggregate, welch

METRICS = ["SR", "SPL", "SSR", "SSSPL", "NSNPL"]


def _summary(**vals):
    """A summarize()-like result whose every metric is ``vals.get(metric, 0.5)`` (fractions) in both subsets."""
    sub = {m: vals.get(m, 0.5) for m in METRICS}
    return {"ALL": dict(sub, episodes=10), "L>=5": dict(sub, episodes=5)}


def _ablation(per_row):
    return aggregate(experiment_rows("ablation"), per_row, METRICS, ["Exploration Reward", "Distance Reward", "DE-MAE"])


def _by(checks, claim, metric, subset="ALL"):
    return next(k for k in checks if k["claim"] == claim and k["metric"] == metric and k["subset"] == subset)


def test_verdicts_and_welch_against_the_textbook_formula():
    base = [_summary(SSR=x, NSNPL=y) for x, y in [(0.60, 0.40), (0.62, 0.42), (0.61, 0.41)]]
    explore = [_summary(SSR=x) for x in (0.70, 0.72, 0.71, 0.73)]  # SSR clearly up
    distance = [_summary(NSNPL=y) for y in (0.30, 0.31, 0.29)]  # NSNPL clearly down: contradicts the paper
    res = _ablation({"baseline": base, "explore": explore, "distance": distance, "tsrm": [_summary()]})
    checks = check_claims({"ablation": res})
    k = _by(checks, "exploration", "SSR")
    a, b = [60.0, 62.0, 61.0], [70.0, 72.0, 71.0, 73.0]
    va, vb = np.var(a, ddof=1) / 3, np.var(b, ddof=1) / 4
    tstat = (np.mean(b) - np.mean(a)) / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / 2 + vb**2 / 3)
    assert k["diff"] == pytest.approx(np.mean(b) - np.mean(a))
    assert k["p"] == pytest.approx(2 * student.sf(abs(tstat), df), rel=1e-9)
    assert k["verdict"] == "supported" and k["n"] == [3, 4]
    # the 95 % interval of the difference: the same Welch-Satterthwaite t; it excludes 0 exactly when p < 0.05
    assert k["ci95"] == pytest.approx(student.ppf(0.975, df) * math.sqrt(va + vb), rel=1e-9)
    assert k["diff"] - k["ci95"] > 0
    assert k["lower_mean"] == pytest.approx(61.0) and k["higher_mean"] == pytest.approx(71.5)
    # the paper's own difference, from its Table II
    assert k["paper_diff"] == pytest.approx(
        round(PAPER_TABLE_II["explore"]["ALL"]["SSR"] - PAPER_TABLE_II["baseline"]["ALL"]["SSR"], 2)
    )
    assert _by(checks, "distance", "NSNPL")["verdict"] == "contradicted"
    # SSSPL: the same value in every seed of both rows (0.5): no test
    assert _by(checks, "exploration", "SSSPL")["verdict"] == "no spread"
    # tsrm has one seed: a difference but no test; demae was not run
    assert _by(checks, "complement-explore", "SR")["verdict"] == "one seed"
    assert _by(checks, "demae-alone", "SR")["verdict"] == "not run"
    assert _by(checks, "demae-alone", "SR")["diff"] is None
    # every ablation claim, metric and subset is there, nothing of the other experiments
    n = sum(len(c.metrics) for c in CLAIMS if c.experiment == "ablation") * 2
    assert len(checks) == n and {k["experiment"] for k in checks} == {"ablation"}
    assert verdict(1.0, 0.2) == "same sign, n.s." and verdict(-1.0, 0.2) == "opposite sign, n.s."
    assert verdict(-1.0, 0.01) == "contradicted" and verdict(None, None) == "not run"
    assert verdict(1.0, None, 1) == "one seed" and verdict(0.0, None, 3) == "no spread"
    assert summary_line(checks).startswith("not run")  # most checks here have a missing row


def test_threshold_claim_compares_with_the_best_other_row():
    rows = experiment_rows("threshold")
    sr = {"c10": 0.50, "c30": 0.62, "c50": 0.60, "c70": 0.58, "c90": 0.40}
    per_row = {rid: [_summary(SR=v + d, SPL=0.2 + d) for d in (-0.01, 0.0, 0.01)] for rid, v in sr.items()}
    per_row["c70"] = [_summary(SR=0.58 + d, SPL=0.3 + d) for d in (-0.01, 0.0, 0.01)]
    res = aggregate(rows, per_row, ["SR", "SPL"], [])
    checks = check_claims({"threshold": res}, subsets=("ALL",))
    k = _by(checks, "threshold-0.7", "SR")
    assert k["lower"] == "c30" and k["diff"] == pytest.approx(-4.0) and k["verdict"] == "contradicted"
    k = _by(checks, "threshold-0.7", "SPL")
    assert k["lower"] in {"c10", "c30", "c50", "c90"} and k["diff"] == pytest.approx(10.0)
    assert k["verdict"] == "supported" and k["paper_diff"] is None
    md = claims_markdown(checks)
    assert "against the best other row" in md and "C_target = 0.3: 62.0 -> 58.0 (-4.0)" in md
    # the claim's p: Bonferroni over the four other rows (the best one's Welch p times 4) when a row is ahead,
    # the largest p over all of them (intersection-union) when 0.7 is ahead of every one
    k = _by(checks, "threshold-0.7", "SR")
    vals = {r["row"]: r["metrics"]["ALL"]["SR"]["values"] for r in res["rows"]}
    assert k["p"] == pytest.approx(4 * welch(vals["c30"], vals["c70"])[1])
    vals = {r["row"]: r["metrics"]["ALL"]["SPL"]["values"] for r in res["rows"]}
    k = _by(checks, "threshold-0.7", "SPL")
    assert k["p"] == pytest.approx(max(welch(v, vals["c70"])[1] for rid, v in vals.items() if rid != "c70" and v))


def test_threshold_claim_corrects_for_picking_the_best_of_many_rows():
    """Eight rows level with 0.7 but for the best one's noise: alone it looks significant (p < 0.05), over eight
    rows it is not; 0.7 ahead of all rows but one with a wide spread is not significantly best."""
    rows = experiment_rows("threshold")
    level = [(-0.01, 0.0, 0.01)] * 9
    per_row = {r.id: [_summary(SR=0.5 + d, SPL=0.3 + d) for d in ds] for r, ds in zip(rows, level)}
    per_row["c90"] = [_summary(SR=0.525 + d, SPL=0.3 + d) for d in (-0.01, 0.0, 0.01)]  # SR +2.5, p ~ 0.03
    per_row["c70"] = [_summary(SR=0.5 + d, SPL=0.4 + d) for d in (-0.005, 0.0, 0.005)]
    per_row["c10"] = [_summary(SR=0.5 + d, SPL=0.3 + d) for d in (-0.2, 0.0, 0.2)]  # SPL 30 +- 20
    res = aggregate(rows, per_row, ["SR", "SPL"], [])
    checks = check_claims({"threshold": res}, subsets=("ALL",))
    vals = {r["row"]: r["metrics"]["ALL"] for r in res["rows"]}
    k = _by(checks, "threshold-0.7", "SR")
    alone = welch(vals["c90"]["SR"]["values"], vals["c70"]["SR"]["values"])[1]
    assert k["lower"] == "c90" and alone < 0.05 and k["p"] == pytest.approx(min(1.0, 8 * alone))
    assert k["verdict"] == "opposite sign, n.s."
    k = _by(checks, "threshold-0.7", "SPL")
    assert k["diff"] > 0 and k["p"] > 0.05 and k["verdict"] == "same sign, n.s."
    assert k["p"] == pytest.approx(welch(vals["c10"]["SPL"]["values"], vals["c70"]["SPL"]["values"])[1])
    # one other row with a single seed: no test of the whole claim
    per_row["c20"] = per_row["c20"][:1]
    checks = check_claims({"threshold": aggregate(rows, per_row, ["SR", "SPL"], [])}, subsets=("ALL",))
    assert _by(checks, "threshold-0.7", "SPL")["verdict"] == "one seed"


def test_markdown_has_one_table_per_claim_with_both_subsets():
    res = _ablation(
        {"baseline": [_summary(NSNPL=x) for x in (0.40, 0.41)], "distance": [_summary(NSNPL=x) for x in (0.45, 0.46)]}
    )
    md = claims_markdown(check_claims({"ablation": res}))
    block = md.split("**distance reward raises pathfinding efficiency (NSNPL)**")[1].split("**")[0]
    lines = [x for x in block.splitlines() if x.startswith("| ")]
    assert lines[0].startswith("| metric | ALL paper | ALL here | ALL p | ALL verdict | L>=5 paper")
    assert len(lines) == 3 and lines[2].startswith("| NSNPL | +2.3 | 40.5 -> 45.5 (+5.0) | 0.02 | supported | +2.7 |")
    assert "+ distance reward against baseline (ResNet18, baseline reward) (seeds 2/2)" in block
    assert claims_markdown([]) == ""


def test_claims_command(tmp_path, capsys):
    res = _ablation(
        {"baseline": [_summary(SR=x) for x in (0.5, 0.52)], "explore": [_summary(SR=x) for x in (0.6, 0.62)]}
    )
    res["experiment"] = "ablation"
    d = tmp_path / "abl"
    d.mkdir()
    (d / "results.json").write_text(json.dumps(res))
    out, js = tmp_path / "claims.md", tmp_path / "claims.json"
    png = tmp_path / "claims.png"
    assert main(["claims", str(d), "--subset", "ALL", "--out", str(out), "--json", str(js), "--plot", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    assert printed == out.read_text() and "L>=5" not in printed and "(alpha 0.05, Welch's t-test)" in printed
    checks = json.loads(js.read_text())
    assert _by(checks, "complement-explore", "SR")["verdict"] == "not run"
    # errors: one line each, nothing written over
    assert main(["claims", str(tmp_path / "nope")]) == 2
    assert "no results.json" in capsys.readouterr().err
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "results.json").write_text("{not json")
    assert main(["claims", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "not valid JSON" in err and len(err.strip().splitlines()) == 1 and out.read_text() == printed
    assert main(["claims", str(d), str(d)]) == 2
    assert "a second 'ablation' experiment" in capsys.readouterr().err
    (bad / "results.json").write_text(json.dumps({"rows": []}))
    assert main(["claims", str(bad)]) == 2 and "not an experiment's results" in capsys.readouterr().err


def test_missing_and_undefined_values_and_equal_means():
    """None / NaN seeds are dropped (a metric with no finite value is 'not run'); equal means are 'no
    difference', not a sign."""
    res = _ablation(
        {
            "baseline": [_summary(SR=x, SPL=0.4) for x in (0.5, 0.6, 0.55)],
            "explore": [_summary(SR=x) for x in (0.6, 0.5, 0.55)],
            "distance": [_summary(NSNPL=0.46), _summary(NSNPL=0.46)],
        }
    )
    rows = {r["row"]: r for r in res["rows"]}
    rows["explore"]["metrics"]["ALL"]["SSSPL"]["values"] = [None, float("nan")]
    rows["explore"]["metrics"]["ALL"]["SR"]["values"].append(None)
    rows["baseline"]["metrics"]["ALL"]["NSNPL"]["values"] += [float("nan")]
    del rows["distance"]["metrics"]["L>=5"]
    checks = check_claims({"ablation": res})
    assert _by(checks, "exploration", "SSSPL")["verdict"] == "not run"
    k = _by(checks, "complement-explore", "SR")  # tsrm missing
    assert k["verdict"] == "not run" and k["p"] is None and k["ci95"] is None
    k = _by(checks, "distance", "NSNPL")
    assert k["n"] == [3, 2] and k["verdict"] == "no spread" and k["diff"] == pytest.approx(-4.0)
    assert _by(checks, "distance", "NSNPL", "L>=5")["verdict"] == "not run"
    res2 = _ablation(
        {
            "baseline": [_summary(SR=x) for x in (0.5, 0.6)],
            "explore": [_summary(SR=x) for x in (0.6, 0.5)],
            "tsrm": [_summary(SR=x) for x in (0.55, 0.56)],
        }
    )
    k = _by(check_claims({"ablation": res2}), "complement-explore", "SR")
    assert k["diff"] == pytest.approx(0.5) and k["verdict"] == "same sign, n.s."
    assert verdict(0.0, 1.0) == "no difference"


def test_markdown_and_html_are_well_formed():
    res = _ablation(
        {"baseline": [_summary(SR=x) for x in (0.5, 0.52)], "explore": [_summary(SR=x) for x in (0.6, 0.62)]}
    )
    res["rows"][1]["label"] = "explore | <b>"
    checks = check_claims({"ablation": res})
    md = claims_markdown(checks)
    for block in md.split("**")[2::2]:
        table = [x for x in block.splitlines() if x.startswith("|")]
        cols = {len(x.replace("\\|", "").split("|")) for x in table}
        assert len(cols) == 1 and cols == {1 + 4 * 2 + 2}  # metric, 4 columns per subset (both), outer pipes
    assert "explore \\| <b> against" in md
    html = claims_html(checks)
    assert html.count("<tr>") == html.count("</tr>") == len(checks) + 1
    assert "<b>" not in html and "explore | &lt;b&gt;" in html


def test_claims_command_two_experiments_and_bad_outputs(tmp_path, capsys):
    """Both experiments have a row 'demae' with its own label; each claim names its own. An output path that is
    a folder or a plot with an unknown suffix is refused before anything is written."""
    abl = _ablation({"baseline": [_summary(SR=x) for x in (0.5, 0.52)], "demae": [_summary(SR=x) for x in (0.6, 0.62)]})
    pre = aggregate(
        experiment_rows("pretraining"), {"mae": [_summary(SR=0.5)], "demae": [_summary(SR=0.6)]}, ["SR", "SPL"], []
    )
    for name, res in (("ablation", abl), ("pretraining", pre)):
        res["experiment"] = name
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps(res))
    dirs = [str(tmp_path / "ablation"), str(tmp_path / "pretraining")]
    out = tmp_path / "claims.md"
    assert main(["claims", *dirs, "--out", str(out)]) == 0
    md = out.read_text()
    assert "+ DE-MAE alone against baseline" in md and "DE-MAE (ViT) w/o crop against Standard MAE (ViT)" in md
    capsys.readouterr()
    for bad in (["--json", str(tmp_path)], ["--plot", str(tmp_path / "x.txt")]):
        assert main(["claims", *dirs, "--out", str(out), *bad]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and out.read_text() == md
    assert not (tmp_path / "x.txt").exists()


def test_claims_command_under_the_other_protocol(tmp_path, capsys):
    """``--protocol`` reads the same checkpoints' evaluation under the other success protocol (results.json's
    ``other_protocols``, written by ``tsnav experiment``); an experiment not evaluated there is named in one line."""
    res = _ablation(
        {"baseline": [_summary(SSR=x) for x in (0.5, 0.52)], "explore": [_summary(SSR=x) for x in (0.5, 0.51)]}
    )
    lin = _ablation(
        {"baseline": [_summary(SSR=x) for x in (0.5, 0.52)], "explore": [_summary(SSR=x) for x in (0.8, 0.82)]}
    )
    res.update(experiment="ablation", protocol="paper")
    lin.update(experiment="ablation", protocol="lineage", trained_protocol="paper")
    d = tmp_path / "abl"
    d.mkdir()
    (d / "results.json").write_text(json.dumps({**res, "other_protocols": {"lineage": lin}}))
    js_paper, js_lin = tmp_path / "paper.json", tmp_path / "lineage.json"
    assert main(["claims", str(d), "--subset", "ALL", "--json", str(js_paper)]) == 0
    assert main(["claims", str(d), "--subset", "ALL", "--json", str(js_lin), "--protocol", "lineage"]) == 0
    js_own = tmp_path / "own.json"
    assert main(["claims", str(d), "--subset", "ALL", "--json", str(js_own), "--protocol", "paper"]) == 0
    capsys.readouterr()
    paper, lineage, own = (_by(json.loads(f.read_text()), "exploration", "SSR") for f in (js_paper, js_lin, js_own))
    assert math.isclose(paper["diff"], -0.5) and math.isclose(lineage["diff"], 30.0) and own == paper
    # a damaged second table is refused in one line too
    (d / "results.json").write_text(json.dumps({**res, "other_protocols": {"lineage": {"rows": [{"row": 1}]}}}))
    assert main(["claims", str(d), "--protocol", "lineage"]) == 2
    assert "no results under the lineage protocol" in capsys.readouterr().err
    (d / "results.json").write_text(json.dumps({**res, "other_protocols": None}))
    assert main(["claims", str(d), "--protocol", "lineage"]) == 2
    assert "no results under the lineage protocol" in capsys.readouterr().err
    # trained under paper and never evaluated under lineage: one line that says how to get it
    (d / "results.json").write_text(json.dumps(res))
    assert main(["claims", str(d), "--protocol", "lineage"]) == 2
    err = capsys.readouterr().err
    assert "no results under the lineage protocol" in err and len(err.strip().splitlines()) == 1
