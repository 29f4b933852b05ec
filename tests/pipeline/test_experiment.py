"""Experiments on the tiny world with very short budgets: all rows produced, resume skips finished jobs, tables
well formed (Markdown / CSV parse, intervals sane), the threshold plot, the report of an experiment folder.

The trainer is injected as a small stand-in in these tests only (it writes a real run folder
with an untrained agent, so evaluation loads it with :func:`tsnav.rl.checkpoint.load_policy`)."""

import csv
import io
import json
import math
import re
import shutil

import numpy as np
import pytest

from tsnav.pipeline.experiment import Experiment, train_config_for
from tsnav.pipeline.config import ExperimentConfig, ScaleConfig, experiment_rows
from tsnav.report.tables import CSV_FIELDS, aggregate, csv_table, markdown_table, mean_ci
from tsnav.metrics import METRICS

from rl_helpers import StandInTrainer

TINY = ScaleConfig().override(
    pretrain=dict(model="vit_micro", patch_size=8, img_size=32, steps=2, batch_size=8),
    feature_batch_size=256,
    train=dict(num_envs=4, updates=2),
    test_per_room_type=6,
    val_per_room_type=6,
    detector=dict(steps=4, batch_size=8, max_states_per_scene=24),
)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def exp_world(tiny_world, tmp_path_factory):
    """A copy of the tiny world without learned tables: the experiments here train their detector and write
    ``detections_learned.hdf5`` into it (the session's tiny world stays as it was)."""
    root = tmp_path_factory.mktemp("exp_world") / "world"
    shutil.copytree(tiny_world, root, ignore=shutil.ignore_patterns("detections_learned*"))
    return root


@pytest.fixture(scope="module")
def pretrain_dir(tmp_path_factory):
    """Pretraining runs shared by the experiments of this module (as ``--pretrain-dir`` lets users do)."""
    return tmp_path_factory.mktemp("pretrain")


def test_mean_ci_against_hand_values():
    m, h = mean_ci([1.0, 2.0, 3.0])
    assert m == 2.0 and h == pytest.approx(4.302652729911275 * 1.0 / math.sqrt(3))  # t(0.975, 2) = 4.3027
    assert mean_ci([5.0]) == (5.0, None) and mean_ci([]) == (None, None)
    m, h = mean_ci([2.0, 2.0, 2.0, 2.0])
    assert m == 2.0 and h == 0.0


def test_rows_match_the_paper():
    abl = experiment_rows("ablation")
    assert [(r.encoder, r.reward) for r in abl] == [
        ("resnet18", "baseline"),
        ("resnet18", "explore"),
        ("resnet18", "distance"),
        ("resnet18", "tsrm"),
        ("demae", "baseline"),
        ("demae", "tsrm"),
        ("demae", "tsrm"),
    ]
    assert [r.flags["DE-MAE"] for r in abl] == [0, 0, 0, 0, 1, 1, 1]
    # issue 14: every row reads the experiment's table (the learned detector's by default) except the labelled
    # oracle-switch row
    assert [r.detections_of("learned") for r in abl] == ["learned"] * 6 + ["oracle"]
    assert abl[-1].label == "TSRM + DE-MAE, oracle switch"
    assert ExperimentConfig(experiment="ablation", data="d", out="o").detections == "learned"
    pre = experiment_rows("pretraining", vc1=True)
    assert [r.encoder for r in pre] == ["resnet18", "vc1", "mae", "demae-crop", "demae"]
    assert all(r.reward == "baseline" for r in pre)
    thr = experiment_rows("threshold")
    assert [r.c_target for r in thr] == pytest.approx([0.1 * k for k in range(1, 10)])
    with pytest.raises(ValueError, match="unknown experiment"):
        experiment_rows("nope")


def _summary(sr):
    sub = {m: sr for m in METRICS}
    return {"ALL": dict(sub, episodes=10, K_nav=5), "L>=5": dict(sub, episodes=5, K_nav=2)}


def test_tables_parse():
    rows = experiment_rows("ablation")
    per_row = {"baseline": [_summary(0.5), _summary(0.6), _summary(0.7)], "explore": [_summary(0.4)]}
    res = aggregate(rows, per_row, list(METRICS), ["Exploration Reward", "Distance Reward", "DE-MAE"])
    md = markdown_table(res).strip().splitlines()
    assert len(md) == 2 + len(rows)
    ncols = len(md[0].split("|"))
    assert all(len(line.split("|")) == ncols for line in md)
    assert "60.00 ± " in md[2] and "| 3 |" in md[2]
    assert "| 40.00 |" in md[3]  # one seed: no interval
    table = list(csv.DictReader(io.StringIO(csv_table(res))))
    assert tuple(table[0]) == CSV_FIELDS
    assert len(table) == len(rows) * 2 * len(METRICS)
    b = [r for r in table if r["row"] == "baseline" and r["subset"] == "ALL" and r["metric"] == "SR"][0]
    assert float(b["mean"]) == pytest.approx(60.0)
    assert float(b["ci_low"]) < 60.0 < float(b["ci_high"])
    assert float(b["ci95"]) == pytest.approx(4.302652729911275 * 10.0 / math.sqrt(3), rel=1e-4)


def test_welch_against_the_baseline():
    """Welch's test of each row against the baseline equals the textbook formula (Welch-Satterthwaite degrees of
    freedom, two-sided Student t tail); too few seeds give no p-value; the Markdown lists every other row."""
    from scipy.stats import t as student

    from tsnav.report.tables import welch, welch_against, welch_markdown

    a, b = [50.0, 60.0, 70.0], [72.0, 75.0, 81.0, 77.0]
    va, vb = np.var(a, ddof=1) / len(a), np.var(b, ddof=1) / len(b)
    tstat = (np.mean(b) - np.mean(a)) / math.sqrt(va + vb)
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    diff, p = welch(a, b)
    assert diff == pytest.approx(np.mean(b) - np.mean(a))
    assert p == pytest.approx(2 * student.sf(abs(tstat), df), rel=1e-9)
    assert welch([1.0], [2.0, 3.0]) == (pytest.approx(1.5), None) and welch([], [1.0]) == (None, None)
    assert welch([1.0, 1.0], [1.0, 1.0]) == (0.0, None)
    rows = experiment_rows("ablation")
    per_row = {
        "baseline": [_summary(x) for x in (0.5, 0.6, 0.7)],
        "explore": [_summary(x) for x in (0.72, 0.75, 0.81, 0.77)],
        "tsrm": [_summary(0.9)],
    }
    res = aggregate(rows, per_row, list(METRICS), ["Exploration Reward", "Distance Reward", "DE-MAE"])
    res["welch"] = welch_against(res, "baseline")
    w = res["welch"]["rows"]
    assert set(w) == {r.id for r in rows} - {"baseline"}
    assert w["explore"]["ALL"]["SR"]["p"] == pytest.approx(p, rel=1e-6)
    assert w["tsrm"]["ALL"]["SR"]["diff"] == pytest.approx(30.0) and w["tsrm"]["ALL"]["SR"]["p"] is None
    assert w["distance"]["ALL"]["SR"]["diff"] is None
    md = welch_markdown(res).strip().splitlines()
    assert (
        len(md) == 2 + len(rows) - 1
        and f"(p {p:.2f})" in md[2]
        and "+30.0 (p -)" in next(x for x in md if "+ both (TSRM)" in x)
    )
    assert welch_against(res, "nosuch") == {} and welch_markdown({"welch": {}}) == ""


def test_ablation_runs_resumes_and_reports(tmp_path, exp_world, pretrain_dir, capsys, monkeypatch):
    out = tmp_path / "ablation"
    cfg = ExperimentConfig(
        experiment="ablation",
        data=str(exp_world),
        out=str(out),
        scale="small",
        seeds=2,
        device="cpu",
        pretrain_dir=str(pretrain_dir),
    )
    trainer = StandInTrainer()
    res = Experiment(cfg, train_fn=trainer, scale=TINY).run()
    assert len(trainer.calls) == 14
    assert {c[0] for c in trainer.calls} == {"baseline", "explore", "distance", "tsrm"}
    assert sorted(set(trainer.detections)) == ["learned", "oracle"] and trainer.detections.count("oracle") == 2
    feats = {c[1] for c in trainer.calls}
    assert (
        len(feats) == 2 and any(f.startswith("resnet18-") for f in feats) and any(f.startswith("demae-") for f in feats)
    )
    assert [r["n"] for r in res["rows"]] == [2] * 7
    # the oracle-switch row was evaluated on the oracle's table, the others on the learned detector's; both
    # tables' quality recorded and printed under the table
    ev = {
        j: json.loads((out / "jobs" / j / "eval" / "metrics.json").read_text())["detections"]
        for j in ("tsrm_demae_s0", "tsrm_demae_oracle_s1")
    }
    assert ev == {"tsrm_demae_s0": "learned", "tsrm_demae_oracle_s1": "oracle"}
    quality = json.loads((out / "detector_quality.json").read_text())
    assert sorted(quality) == ["learned", "oracle"] and quality["learned"]["fingerprint"].startswith("learned-")
    assert 0.0 <= quality["learned"]["reach"] <= 1.0 and quality["oracle"]["pairs"] == quality["learned"]["pairs"]
    for r in res["rows"]:
        for s in ("ALL", "L>=5"):
            for m in METRICS:
                v = r["metrics"][s][m]
                assert 0.0 <= v["mean"] <= 100.0 and v["ci95"] is not None and v["ci95"] >= 0.0
                assert len(v["values"]) == 2
    for j in json.loads((out / "experiment.json").read_text())["jobs"]:
        d = out / j["dir"]
        assert (d / "DONE").exists() and (d / "eval" / "records.jsonl").exists()
        assert (d / "eval" / "trajectories.jsonl").exists()
    # the pretraining runs and feature caches are there
    assert (pretrain_dir / "demae" / "encoder.safetensors").exists()
    assert (pretrain_dir / "resnet18-sup" / "encoder.safetensors").exists()
    md = (out / "table.md").read_text()
    md, other_md = md.split("### The same agents under the `lineage` protocol")
    table, welch_part = md.split("Welch's t-test")
    welch_part, claims_part = welch_part.split("Against the paper's claims")
    assert "**exploration reward raises search success" in claims_part and "| NSNPL | +2.3 |" in claims_part
    assert table.count("\n| ") == 9 and "| TSRM + DE-MAE, oracle switch |" in table
    assert welch_part.count("\n| ") == 2 * 8 and "| ALL: row vs baseline (ResNet18, baseline reward) |" in welch_part
    assert "| L>=5: row vs" in welch_part
    assert "Done dips (fewer than 5 % of training episodes ending with Done): 0 of 14 jobs." in welch_part
    assert json.loads((out / "results.json").read_text())["done_dips"] == {"jobs": 14, "with_dips": []}
    assert "Detections: learned; row 'TSRM + DE-MAE, oracle switch': oracle" in md
    assert "Success protocol: paper (trained and evaluated) - Done succeeds" in md.splitlines()[2]
    assert json.loads((out / "results.json").read_text())["protocol"] == "paper"
    assert json.loads((out / "episodes_test.json").read_text())["protocol"] == "paper"
    assert "- detections_learned on" in md and "- detections_oracle on" in md and "reach of 0.7" in md
    rows = list(csv.DictReader(open(out / "table.csv")))
    assert len(rows) == 7 * 2 * len(METRICS)
    # the same checkpoints under the other protocol: its own episode list, a folder per job, a second table
    assert json.loads((out / "episodes_test_lineage.json").read_text())["protocol"] == "lineage"
    for j in json.loads((out / "experiment.json").read_text())["jobs"]:
        main_eval, other = (
            json.loads((out / j["dir"] / e / "metrics.json").read_text()) for e in ("eval", "eval_lineage")
        )
        assert (other["protocol"], other["trained_protocol"], main_eval["protocol"]) == ("lineage", "paper", "paper")
        assert (other["run"], other["checkpoint"], other["detections"]) == (
            main_eval["run"],
            "best",
            main_eval["detections"],
        )
    lin = json.loads((out / "results.json").read_text())["other_protocols"]["lineage"]
    assert (
        lin["protocol"] == "lineage" and lin["trained_protocol"] == "paper" and [r["n"] for r in lin["rows"]] == [2] * 7
    )
    sr = {r["row"]: r["metrics"]["ALL"]["SR"]["values"] for r in lin["rows"]}
    assert sr["tsrm"] == [
        100
        * json.loads((out / "jobs" / f"tsrm_s{k}" / "eval_lineage" / "metrics.json").read_text())["metrics"]["ALL"][
            "SR"
        ]
        for k in (0, 1)
    ]
    assert "protocol: lineage (agent trained under paper) - Done succeeds" in other_md
    assert other_md.count("| TSRM + DE-MAE, oracle switch |") == 3 and "under `lineage`:" in other_md  # table, 2 Welch
    assert "Against the paper's claims under `lineage`" in other_md
    assert len(list(csv.DictReader(open(out / "table_lineage.csv")))) == 7 * 2 * len(METRICS)

    # every job evaluated the checkpoint chosen on the validation episodes (its `best`), and says which
    sel_eps = json.loads((out / "episodes_select.json").read_text())
    assert sel_eps["split"] == "val" and len(sel_eps["episodes"]) > 0
    for j in json.loads((out / "experiment.json").read_text())["jobs"]:
        d = out / j["dir"]
        ck = json.loads((d / "DONE").read_text())["checkpoint"]
        sel = json.loads((d / "train" / "selection.json").read_text())
        assert ck["kind"] == "best" and ck["name"] == sel["best"] and (d / "train" / "best" / "state.json").exists()
        assert ck["val_SR"] == sel["scores"][ck["name"]]["metrics"]["ALL"]["SR"] and ck["update"] == 3

    # resume: nothing left to train; one unfinished job is redone, its selection.json reused (no checkpoint
    # scored again); a job interrupted before selection selects on resume
    capsys.readouterr()
    (out / "jobs" / "explore_s1" / "DONE").unlink()
    again = StandInTrainer()
    Experiment(cfg, train_fn=again, scale=TINY).run()
    assert again.calls == [("explore", again.calls[0][1], 0.7, 1)]
    printed = capsys.readouterr().out
    assert "13 finished, 1 to run" in printed and "selecting explore_s1" in printed
    assert "explore_s1 under the lineage protocol" in printed  # a job run again is evaluated there again
    # an evaluation under the other protocol that is missing (interrupted, or a folder from before) is made
    shutil.rmtree(out / "jobs" / "baseline_s1" / "eval_lineage")
    Experiment(cfg, train_fn=again, scale=TINY).run()
    printed = capsys.readouterr().out
    assert "14 finished, 0 to run" in printed and "baseline_s1 under the lineage protocol" in printed
    assert (out / "jobs" / "baseline_s1" / "eval_lineage" / "metrics.json").exists()
    # a job that cannot be evaluated there is named, left out of the second table (which says so), and the main
    # table is written all the same
    shutil.rmtree(out / "jobs" / "baseline_s1" / "eval_lineage")
    real_evaluate = Experiment.evaluate

    def failing(self, job, checkpoint, protocol=None):
        if protocol == "lineage" and job.row.id == "baseline" and job.seed == 1:
            raise ValueError("cannot load this run")
        return real_evaluate(self, job, checkpoint, protocol)

    monkeypatch.setattr(Experiment, "evaluate", failing)
    (out / "table.md").unlink()
    Experiment(cfg, train_fn=again, scale=TINY).run()
    monkeypatch.undo()
    assert "baseline_s1 not evaluated under lineage: cannot load this run" in capsys.readouterr().out
    md_again = (out / "table.md").read_text()
    assert (
        "Not every finished job is evaluated under `lineage` yet (fewer seeds than above): baseline (ResNet18, "
        "baseline reward)."
    ) in md_again
    lin = json.loads((out / "results.json").read_text())["other_protocols"]["lineage"]
    assert lin["incomplete_rows"] == ["baseline (ResNet18, baseline reward)"] and lin["rows"][0]["n"] == 1
    assert [r["n"] for r in json.loads((out / "results.json").read_text())["rows"]] == [2] * 7
    Experiment(cfg, train_fn=again, scale=TINY).run()  # evaluated there on the next run
    assert "incomplete_rows" not in json.loads((out / "results.json").read_text())["other_protocols"]["lineage"]
    assert not re.search(r"^ +\S+: SR [0-9.]+, SPL [0-9.]+$", printed, re.M)  # select_checkpoint's score line
    for f in ("DONE", "train/selection.json"):
        (out / "jobs" / "tsrm_s0" / f).unlink()
    shutil.rmtree(out / "jobs" / "tsrm_s0" / "train" / "best")
    Experiment(cfg, train_fn=StandInTrainer(), scale=TINY).run()
    assert (out / "jobs" / "tsrm_s0" / "train" / "selection.json").exists()
    assert json.loads((out / "jobs" / "tsrm_s0" / "DONE").read_text())["checkpoint"]["kind"] == "best"
    assert "13 finished, 1 to run" in capsys.readouterr().out

    # another scale in the same folder is refused
    with pytest.raises(ValueError, match="another scale"):
        Experiment(ExperimentConfig(**{**cfg.__dict__, "scale": "paper"}), train_fn=again).run()
    with pytest.raises(ValueError, match=r"another protocol \('paper', now 'lineage'\)"):
        Experiment(ExperimentConfig(**{**cfg.__dict__, "protocol": "lineage"}), train_fn=again).run()
    # agents were evaluated greedily (recorded); sampling them in the same folder is refused, and so is
    # resuming a folder from before the key existed (its agents were sampled) without --sample
    assert json.loads((out / "jobs" / "tsrm_s0" / "eval" / "metrics.json").read_text())["sample"] is False
    with pytest.raises(ValueError, match="another sample"):
        Experiment(ExperimentConfig(**{**cfg.__dict__, "sample": True}), train_fn=again).run()
    doc = json.loads((out / "experiment.json").read_text())
    del doc["config"]["sample"]
    (out / "experiment.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"another sample \(True, now False\)"):
        Experiment(cfg, train_fn=again).run()
    doc["config"]["sample"] = False
    # folders from before checkpoint selection evaluated the latest checkpoint: not mixed with new jobs
    del doc["config"]["checkpoint"]
    (out / "experiment.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"another checkpoint \('latest', now 'best'\)"):
        Experiment(cfg, train_fn=again).run()
    doc["config"]["checkpoint"] = "best"
    (out / "experiment.json").write_text(json.dumps(doc))

    from tsnav.report.html import build_report

    html = build_report(out, gallery=2).read_text()
    assert "Experiment: ablation" in html and "14 of 14 jobs finished" in html and "&#10003;" in html
    other_html = html.split("The same agents under the lineage protocol")[1].split("</table>")[0]
    assert "protocol: lineage (agent trained under paper)" in other_html and other_html.count("<tr>") == 2 + 7
    assert "TSRM + DE-MAE, oracle switch" in html and "detections_learned on" in html
    assert "Against the paper's claims" in html and "exploration reward raises search success" in html
    assert "alt='claims'" in html
    assert "Encoders" in html and html.count("recon_") == 1  # DE-MAE; the ResNet18 run has no reconstructions
    assert html.count("_map.png") == 2


def test_threshold_experiment_plot(tmp_path, exp_world, pretrain_dir):
    out = tmp_path / "thr"
    cfg = ExperimentConfig(
        experiment="threshold", data=str(exp_world), out=str(out), seeds=1, device="cpu", pretrain_dir=str(pretrain_dir)
    )
    trainer = StandInTrainer()
    res = Experiment(cfg, train_fn=trainer, scale=TINY).run()
    assert sorted(c[2] for c in trainer.calls) == pytest.approx([0.1 * k for k in range(1, 10)])
    assert len(res["rows"]) == 9 and all(r["n"] == 1 for r in res["rows"])
    assert json.loads((out / "jobs" / "c30_s0" / "eval" / "metrics.json").read_text())["config"]["c_target"] == 0.3
    ep = json.loads((out / "episodes_val.json").read_text())
    assert ep["split"] == "val" and len(ep["episodes"]) > 0
    from PIL import Image

    img = np.asarray(Image.open(out / "threshold.png").convert("RGB"))
    assert img.shape[1] > 1000
    red = (img[..., 0] > 200) & (img[..., 1] < 60) & (img[..., 2] < 60)
    assert red.sum() > 50  # the best points are starred
    # the same agent (one seed) at a higher threshold switches stage later or never, never earlier
    from tsnav.metrics import read_records

    switch = np.array(
        [
            [
                1000 if r.pathfinding_start_step is None else r.pathfinding_start_step
                for r in read_records(out / "jobs" / f"c{10 * k:02d}_s0" / "eval" / "records.jsonl")
            ]
            for k in range(1, 10)
        ]
    )
    assert (np.diff(switch, axis=0) >= 0).all()
    ssr = [r["metrics"]["ALL"]["SSR"]["mean"] for r in res["rows"]]
    assert all(a >= b - 1e-9 for a, b in zip(ssr, ssr[1:]))


def test_training_budget_in_updates_or_minutes():
    """Budgets are in updates by default (the same agent on a busy machine); --updates-per-job or
    --minutes-per-job replace the scale's; with both, the first reached stops training."""
    from tsnav.pipeline.config import SCALES

    row = experiment_rows("ablation")[0]
    scale = ScaleConfig()  # small: 1000 updates, no minute limit

    def budget(sc=scale, **kw):
        tc, _ = train_config_for(ExperimentConfig(experiment="ablation", data="d", out="o", **kw), sc, row, "f", 0)
        return tc.minutes, tc.updates

    assert budget() == (None, 1000)
    for name, sc in SCALES.items():  # no scale trains for a number of minutes
        assert sc.train.minutes is None and (sc.train.updates or sc.train.episodes), name
    assert budget(minutes_per_job=2.5) == (2.5, None)
    assert budget(updates_per_job=700) == (None, 700)
    assert budget(updates_per_job=700, minutes_per_job=3.0) == (3.0, 700)
    for p in ("paper", "lineage"):  # the experiment's protocol is every job's
        tc, _ = train_config_for(
            ExperimentConfig(experiment="ablation", data="d", out="o", protocol=p), scale, row, "f", 0
        )
        assert tc.protocol == p


def test_jobs_keep_milestones_for_selection():
    """Each scale keeps a handful of milestones per job, on checkpoint updates; --checkpoint latest keeps none."""
    from dataclasses import replace

    from tsnav.pipeline.config import SCALES

    row = experiment_rows("ablation")[0]
    for name, sc in SCALES.items():
        if sc.train.updates and sc.train.milestone_every:
            assert 3 <= sc.train.updates // sc.train.milestone_every <= 10, name
    cfg = ExperimentConfig(experiment="ablation", data="d", out="o")
    tc, _ = train_config_for(cfg, SCALES["small"], row, "f", 0)
    assert (tc.milestone_every, tc.checkpoint_every) == (200, 100)
    tc, _ = train_config_for(cfg, SCALES["small"].override(train=dict(milestone_every=30)), row, "f", 0)
    assert (tc.milestone_every, tc.checkpoint_every) == (30, 10)
    tc, _ = train_config_for(replace(cfg, checkpoint="latest"), SCALES["small"], row, "f", 0)
    assert (tc.milestone_every, tc.checkpoint_every) == (None, 100)
    with pytest.raises(ValueError, match="--checkpoint must be one of"):
        Experiment(replace(cfg, checkpoint="first"))


def test_experiment_command_errors(tmp_path, tiny_world, capsys):
    from tsnav.cli import main

    assert main(["experiment", "ablation", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "no such dataset folder" in capsys.readouterr().err
    w = tmp_path / "w.safetensors"
    w.write_bytes(b"")
    assert (
        main(
            ["experiment", "ablation", "--data", str(tiny_world), "--out", str(tmp_path / "o"), "--vc1-weights", str(w)]
        )
        == 2
    )
    assert "pretraining experiment only" in capsys.readouterr().err
    assert (
        main(["experiment", "threshold", "--data", str(tiny_world), "--out", str(tmp_path / "o"), "--seeds", "0"]) == 2
    )
    assert "--seeds must be >= 1" in capsys.readouterr().err
    assert (
        main(
            [
                "experiment",
                "ablation",
                "--data",
                str(tiny_world),
                "--out",
                str(tmp_path / "o"),
                "--updates-per-job",
                "0",
            ]
        )
        == 2
    )
    assert "--updates-per-job must be >= 1" in capsys.readouterr().err
    assert (
        main(["experiment", "ablation", "--data", str(tiny_world), "--out", str(tmp_path / "o"), "--protocol", "1.5"])
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "unknown success protocol '1.5'" in err and len(err.splitlines()) == 1 and not (tmp_path / "o").exists()
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "experiment.json").write_text("{not json")
    assert main(["experiment", "ablation", "--data", str(tiny_world), "--out", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "unreadable experiment file" in err and len(err.strip().splitlines()) == 1
    assert (bad / "experiment.json").read_text() == "{not json"  # left as it was


def test_pretraining_experiment_with_the_real_trainer(tmp_path, exp_world, pretrain_dir):
    """The default trainer (tsnav.rl.train.train_run), two updates per job, two jobs at once in worker processes."""
    from tsnav.rl.checkpoint import read_run_config

    scale = TINY.override(train=dict(minutes=None, updates=2, num_envs=4, milestone_every=1))
    out = tmp_path / "pre"
    cfg = ExperimentConfig(
        experiment="pretraining",
        data=str(exp_world),
        out=str(out),
        seeds=1,
        device="cpu",
        pretrain_dir=str(pretrain_dir),
        parallel=2,
    )
    res = Experiment(cfg, scale=scale).run()
    assert [r["row"] for r in res["rows"]] == ["resnet18", "mae", "demae_crop", "demae"]
    assert all(r["n"] == 1 for r in res["rows"]) and res["metrics"] == ["SR", "SPL"]
    feats = set()
    for r in res["rows"]:
        run = read_run_config(out / "jobs" / f"{r['row']}_s0" / "train")
        assert run["train"]["reward"] == "baseline" and run["train"]["updates"] == 2
        assert run["train"]["minutes"] is None and run["train"]["milestone_every"] == 1
        feats.add(run["train"]["features"])
        # both milestones (updates 1 and 2) scored on validation; the best by SR, SPL, then earliest
        done = json.loads((out / "jobs" / f"{r['row']}_s0" / "DONE").read_text())
        scores = json.loads((out / "jobs" / f"{r['row']}_s0" / "train" / "selection.json").read_text())["scores"]
        assert sorted(s["update"] for s in scores.values()) == [1, 2] and done["checkpoint"]["candidates"] == 2
        best = max(scores.values(), key=lambda s: (s["metrics"]["ALL"]["SR"], s["metrics"]["ALL"]["SPL"], -s["update"]))
        assert done["checkpoint"]["update"] == best["update"]
    assert len(feats) == 4
    md = (out / "table.md").read_text()
    assert "ALL SR" in md and "L>=5 SPL" in md and "SSR" not in md


def test_pretraining_reuses_the_ablations_jobs(tmp_path, exp_world, pretrain_dir, capsys):
    """--reuse-from: the pretraining table's ResNet18 and DE-MAE rows (baseline reward) are the ablation's
    "baseline" and "+ DE-MAE alone" jobs: copied, not trained again, then selected and evaluated here."""
    abl = tmp_path / "abl"
    base = dict(data=str(exp_world), seeds=1, device="cpu", pretrain_dir=str(pretrain_dir))
    Experiment(
        ExperimentConfig(experiment="ablation", out=str(abl), **base), train_fn=StandInTrainer(), scale=TINY
    ).run()
    pre = tmp_path / "pre"
    trainer = StandInTrainer()
    capsys.readouterr()
    res = Experiment(
        ExperimentConfig(experiment="pretraining", out=str(pre), reuse_from=(str(abl),), **base),
        train_fn=trainer,
        scale=TINY,
    ).run()
    assert sorted(c[1].split("-")[0] for c in trainer.calls) == ["demae", "mae"]  # MAE and the crop variant only
    out = capsys.readouterr().out
    assert out.count("reusing the trained run") == 2 and str(abl / "jobs" / "baseline_s0" / "train") in out
    assert all(r["n"] == 1 for r in res["rows"])
    for row, src in (("resnet18", "baseline"), ("demae", "demae")):
        a = abl / "jobs" / f"{src}_s0" / "train"
        b = pre / "jobs" / f"{row}_s0" / "train"
        assert json.loads((b / "config.json").read_text()) == json.loads((a / "config.json").read_text())
        assert (b / "selection.json").exists() and (b / "best").is_dir()  # selected again, here
        assert not (b.parent / "train.copying").exists()
    # nothing to reuse for another seed; a folder that is no experiment is refused
    tc1, _ = train_config_for(
        ExperimentConfig(experiment="pretraining", out="x", **base),
        TINY,
        experiment_rows("pretraining")[0],
        "resnet18-x",
        1,
    )
    exp2 = Experiment(
        ExperimentConfig(experiment="pretraining", out=str(tmp_path / "pre2"), reuse_from=(str(abl),), **base),
        train_fn=StandInTrainer(),
        scale=TINY,
    )
    assert exp2.reusable_run(tc1) is None
    exp3 = Experiment(
        ExperimentConfig(experiment="pretraining", out=str(tmp_path / "pre3"), reuse_from=(str(tmp_path),), **base),
        train_fn=StandInTrainer(),
        scale=TINY,
    )
    with pytest.raises(ValueError, match="not an experiment folder"):
        exp3.reusable_run(tc1)


def test_blocked_action_experiment(tmp_path, exp_world, pretrain_dir, capsys):
    """--blocked-action (a deviation): every job's agent gets the flag, table.md and results.json say so, the folder
    refuses a resume without it, and --reuse-from does not copy a run whose agent lacks it."""
    from dataclasses import replace

    from tsnav.rl.checkpoint import read_run_config

    base = dict(data=str(exp_world), seeds=1, device="cpu", pretrain_dir=str(pretrain_dir), rows=("baseline",))
    row = experiment_rows("ablation")[0]
    cfg = ExperimentConfig(experiment="ablation", out=str(tmp_path / "flag"), blocked_action=True, **base)
    _, agent = train_config_for(cfg, TINY, row, "f", 0)
    _, plain = train_config_for(replace(cfg, blocked_action=False), TINY, row, "f", 0)
    assert agent.blocked_action and not plain.blocked_action
    assert replace(agent, blocked_action=False) == plain  # nothing else changes
    trainer = StandInTrainer()
    res = Experiment(cfg, train_fn=trainer, scale=TINY).run()
    assert res["blocked_action"] is True and trainer.calls
    run = read_run_config(tmp_path / "flag" / "jobs" / "baseline_s0" / "train")
    assert run["agent"]["blocked_action"] is True
    assert "`--blocked-action`, a deviation" in (tmp_path / "flag" / "table.md").read_text()
    with pytest.raises(ValueError, match="another blocked_action"):
        Experiment(replace(cfg, blocked_action=False), train_fn=StandInTrainer(), scale=TINY).run()
    # a plain experiment beside it: the flagged run is not reused for it, an identical one would be
    plain_exp = Experiment(
        ExperimentConfig(
            experiment="ablation", out=str(tmp_path / "plain"), reuse_from=(str(tmp_path / "flag"),), **base
        ),
        train_fn=StandInTrainer(),
        scale=TINY,
    )
    tc, plain_agent = train_config_for(plain_exp.cfg, TINY, row, run["train"]["features"], 0)
    assert plain_exp.reusable_run(tc, plain_agent) is None
    assert plain_exp.reusable_run(tc, agent) == tmp_path / "flag" / "jobs" / "baseline_s0" / "train"


def test_select_per_room_type(tmp_path, exp_world, pretrain_dir):
    """--select-per-room-type: the selection episodes hold that many per room type, table.md and results.json say so,
    the folder refuses a resume with another value, and a count below 1 is refused before any work."""
    from dataclasses import replace

    from tsnav.sim.episodes import read_episodes

    cfg = ExperimentConfig(
        experiment="ablation",
        data=str(exp_world),
        out=str(tmp_path / "sel"),
        seeds=1,
        device="cpu",
        pretrain_dir=str(pretrain_dir),
        rows=("baseline",),
        select_per_room_type=3,
    )
    res = Experiment(cfg, train_fn=StandInTrainer(), scale=TINY).run()
    assert res["select_per_room_type"] == 3
    eps, meta = read_episodes(tmp_path / "sel" / "episodes_select.json")
    per_type = {}
    for e in eps:
        per_type[e.room_type] = per_type.get(e.room_type, 0) + 1
    assert per_type and max(per_type.values()) == 3 and meta["per_room_type"] == 3
    assert "chosen on 3 validation episodes per room type" in (tmp_path / "sel" / "table.md").read_text()
    with pytest.raises(ValueError, match="another select_per_room_type"):
        Experiment(replace(cfg, select_per_room_type=None), train_fn=StandInTrainer(), scale=TINY).run()
    for bad in (0, 2.5, True):
        with pytest.raises(ValueError, match="--select-per-room-type must be an integer >= 1"):
            Experiment(
                replace(cfg, out=str(tmp_path / "zero"), select_per_room_type=bad),
                train_fn=StandInTrainer(),
                scale=TINY,
            )
    with pytest.raises(ValueError, match="needs --checkpoint best"):
        Experiment(
            replace(cfg, out=str(tmp_path / "latest"), checkpoint="latest"), train_fn=StandInTrainer(), scale=TINY
        )
    assert not (tmp_path / "zero").exists() and not (tmp_path / "latest").exists()
    # without the option the scale's count is used, and the table says nothing
    plain = replace(cfg, out=str(tmp_path / "plain"), select_per_room_type=None)
    res = Experiment(plain, train_fn=StandInTrainer(), scale=TINY).run()
    assert res["select_per_room_type"] == TINY.val_per_room_type
    assert "validation episodes per room type" not in (tmp_path / "plain" / "table.md").read_text()
    # naming the scale's own count is the same folder; so is a folder written before the option existed
    trainer = StandInTrainer()
    Experiment(replace(plain, select_per_room_type=TINY.val_per_room_type), train_fn=trainer, scale=TINY).run()
    meta = tmp_path / "plain" / "experiment.json"
    doc = json.loads(meta.read_text())
    doc["config"].pop("select_per_room_type")
    meta.write_text(json.dumps(doc))
    Experiment(plain, train_fn=trainer, scale=TINY).run()
    assert trainer.calls == []  # nothing trained again


def test_rows_option_runs_a_subset_and_adds_the_rest_later(tmp_path, exp_world, pretrain_dir, capsys):
    """--rows: only the named rows are trained and tabulated; a second call into the same folder with the other
    rows trains only those and finds the first call's jobs done; an unknown id is refused in one line."""
    base = dict(
        experiment="pretraining",
        data=str(exp_world),
        out=str(tmp_path / "pre"),
        seeds=1,
        device="cpu",
        pretrain_dir=str(pretrain_dir),
    )
    first = StandInTrainer()
    res = Experiment(ExperimentConfig(rows=("mae", "demae_crop"), **base), train_fn=first, scale=TINY).run()
    assert [r["row"] for r in res["rows"]] == ["mae", "demae_crop"] and len(first.calls) == 2
    assert res.get("welch", {}) == {}  # the baseline row is not among them
    second = StandInTrainer()
    res = Experiment(ExperimentConfig(**base), train_fn=second, scale=TINY).run()
    assert [r["row"] for r in res["rows"]] == ["resnet18", "mae", "demae_crop", "demae"]
    assert sorted(c[1].split("-")[0] for c in second.calls) == ["demae", "resnet18"]  # the other two only
    assert all(r["n"] == 1 for r in res["rows"]) and res["welch"]["baseline"] == "resnet18"
    with pytest.raises(ValueError, match="no row 'dino'.*its rows: resnet18, mae, demae_crop, demae"):
        Experiment(ExperimentConfig(rows=("dino",), **base))
    from tsnav.cli import main

    capsys.readouterr()
    assert (
        main(
            ["experiment", "pretraining", "--data", str(exp_world), "--out", str(tmp_path / "o"), "--rows", "mae,dino"]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert "no row 'dino'" in err and len(err.splitlines()) == 1
