"""tsnav analyze merge-rows: rows of another experiment's results copied into a table, per seed, in the experiment's
row order, with Welch's tests recomputed; refusals in one line, nothing written on a refusal."""

import json

import pytest
from script_helpers import load_analysis


def _row(rid, label, vals, metrics=("SR", "SPL")):
    return {
        "row": rid,
        "label": label,
        "n": len(vals),
        "flags": {},
        "c_target": 0.7,
        "encoder": "x",
        "reward": "baseline",
        "detections": None,
        "metrics": {
            s: {m: {"mean": sum(vals) / len(vals), "ci95": 1.0, "values": list(vals)} for m in metrics}
            for s in ("ALL", "L>=5")
        },
    }


def _results(exp, rows, metrics=("SR", "SPL"), protocol="lineage", other=True):
    d = {
        "experiment": exp,
        "protocol": protocol,
        "detections": "learned4",
        "subsets": ["ALL", "L>=5"],
        "metrics": list(metrics),
        "flag_columns": [],
        "rows": rows,
    }
    if other:
        d["other_protocols"] = {
            "paper": dict(_results(exp, rows, metrics, "paper", other=False), trained_protocol=protocol)
        }
    return d


def test_merge_copies_per_seed_values_in_row_order(tmp_path, capsys):
    mod = load_analysis("merge_rows")
    t3 = tmp_path / "t3"
    t3.mkdir()
    (t3 / "results.json").write_text(
        json.dumps(
            _results(
                "pretraining",
                [
                    _row("mae", "Standard MAE (ViT)", [60.0, 62.0, 64.0]),
                    _row("demae_crop", "DE-MAE (ViT) w/ crop", [61.0, 63.0, 65.0]),
                ],
            )
        )
    )
    m5 = ("SR", "SPL", "SSR", "SSSPL", "NSNPL")
    t2 = tmp_path / "t2.json"
    t2.write_text(
        json.dumps(
            _results(
                "ablation",
                [
                    _row("baseline", "baseline", [50.0, 52.0, 54.0], m5),
                    _row("explore", "+ exploration reward", [1.0, 2.0, 3.0], m5),
                    _row("demae", "+ DE-MAE alone", [70.0, 71.0, 72.0], m5),
                ],
                m5,
            )
        )
    )
    out = tmp_path / "full"
    assert (
        mod.main(
            [
                "--into",
                str(t3),
                "--from",
                str(t2),
                "--map",
                "resnet18=baseline",
                "--map",
                "demae=demae",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    res = json.loads((out / "results.json").read_text())
    assert [r["row"] for r in res["rows"]] == ["resnet18", "mae", "demae_crop", "demae"]
    r18 = res["rows"][0]
    assert r18["label"] == "Baseline (ResNet18)" and r18["merged_from"]["row"] == "baseline"
    assert r18["metrics"]["ALL"]["SR"]["values"] == [50.0, 52.0, 54.0] and set(r18["metrics"]["ALL"]) == {"SR", "SPL"}
    # Welch against the ResNet18 row, recomputed: MAE's mean is 10 points above it
    assert res["welch"]["baseline"] == "resnet18"
    assert res["welch"]["rows"]["mae"]["ALL"]["SR"]["diff"] == pytest.approx(10.0)
    assert res["welch"]["rows"]["demae"]["ALL"]["SR"]["diff"] == pytest.approx(19.0)
    assert [r["row"] for r in res["other_protocols"]["paper"]["rows"]] == ["resnet18", "mae", "demae_crop", "demae"]
    assert "Baseline (ResNet18)" in (out / "table.md").read_text() and "copied from" in capsys.readouterr().out
    # tsnav claims reads the merged folder
    from tsnav.cli import main

    assert main(["claims", str(out)]) == 0


def test_merge_refusals(tmp_path, capsys):
    mod = load_analysis("merge_rows")
    t3 = tmp_path / "t3.json"
    t3.write_text(json.dumps(_results("pretraining", [_row("mae", "MAE", [60.0, 62.0, 64.0])])))
    two = tmp_path / "two.json"
    two.write_text(json.dumps(_results("ablation", [_row("baseline", "b", [50.0, 52.0])])))
    paper = tmp_path / "paper.json"
    paper.write_text(json.dumps(_results("ablation", [_row("baseline", "b", [50.0, 52.0, 54.0])], protocol="paper")))
    bad = tmp_path / "bad.json"
    bad.write_text("{no")
    out = tmp_path / "o"
    cases = [
        (["--from", str(two), "--map", "resnet18=baseline"], "has 2 seeds"),
        (["--from", str(paper), "--map", "resnet18=baseline"], "protocol is 'paper'"),
        (["--from", str(bad), "--map", "resnet18=baseline"], "unreadable results file"),
        (["--from", str(tmp_path / "none.json"), "--map", "resnet18=baseline"], "no such results file"),
        (["--from", str(two), "--map", "resnet18"], "expected TARGET_ROW=SOURCE_ROW"),
        (["--from", str(two), "--map", "mae=baseline"], "already in the target's results"),
    ]
    for extra, msg in cases:
        assert mod.main(["--into", str(t3), "--out", str(out)] + extra) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1, (msg, err)
    assert not out.exists()
