"""The main job on the tiny world with tiny budgets: every stage runs, the report and the results table are
written, a second run reuses every stage, and a removed output is rebuilt with what depends on it.

The trainer is the real one (``tsnav.rl.train.train_run``, two updates of four envs), wrapped to count its calls."""

import json
import shutil
from dataclasses import replace

import pytest

from tsnav.pipeline.demo import STEPS, DemoConfig, run_demo, train_subset
from tsnav.pipeline.config import SCALES
from tsnav.rl.train import train_run

from rl_helpers import RecordingTrainer

TINY = DemoConfig(
    preset="tiny",
    detector="train",
    train_rooms_per_type=1,
    gallery=2,
    scale=SCALES["demo"].override(
        pretrain=dict(model="vit_micro", patch_size=8, img_size=32, steps=2, batch_size=8),
        test_per_room_type=5,
        train=dict(updates=2, num_envs=4),
        detector=dict(steps=4, batch_size=8, max_states_per_scene=24),
    ),
)

#: Copy the tiny world into a demo folder without the learned tables other tests may have written (the demo
#: then trains its own detector).
NO_LEARNED = shutil.ignore_patterns("detections_learned*")


pytestmark = pytest.mark.usefixtures("one_torch_thread")


class CountedTrainer(RecordingTrainer):
    """The real trainer, recording each call's reward, features, C_target, seed and detections."""

    def train(self, tc, agent, run_dir):
        return train_run(tc, agent, run_dir)


def test_train_subset_links_smallest_rooms(tmp_path, tiny_world, tiny_scenes):
    names = train_subset(tiny_world, tmp_path / "sub", 1)
    train = [s for s in tiny_scenes if s.meta.get("split") == "train"]
    by_type = {}
    for s in train:
        by_type.setdefault(s.room_type, []).append((s.num_states, s.name))
    assert names == sorted(min(v)[1] for v in by_type.values())
    assert all((tmp_path / "sub" / n).is_symlink() and (tmp_path / "sub" / n / "COMPLETE").exists() for n in names)
    assert train_subset(tiny_world, tmp_path / "sub", None) == sorted(s.name for s in train)


def test_demo_end_to_end_and_reuse(tmp_path, tiny_world, capsys):
    out = tmp_path / "demo"
    shutil.copytree(tiny_world, out / "world", ignore=NO_LEARNED)  # the world stage then only checks it
    trainer = CountedTrainer()
    res = run_demo(out, TINY, train_fn=trainer)
    # the shipped agent reads 128-px real rooms: on the tiny world its step says why it is left out
    assert [res["steps"][s][0] for s in STEPS] == ["-" if s == "shipped" else "done" for s in STEPS]
    assert list(res["results"]) == ["paper", "lineage"]
    for protocol, rows in res["results"].items():
        assert list(rows) == ["agent (TSRM, DE-MAE)", "agent on the oracle table", "scripted explorer", "random"]
        assert all(r["protocol"] == protocol for r in rows.values())
    # the lineage's list keeps the starts that already see the target; the oracle table's row reads the oracle's
    lin = json.loads((out / "eval" / "explorer_lineage" / "metrics.json").read_text())
    assert lin["protocol"] == "lineage" and lin["episodes_file"].endswith("test_episodes_lineage.json")
    orc = json.loads((out / "eval" / "agent_oracle_lineage" / "metrics.json").read_text())
    assert orc["detections"] == "oracle" and orc["protocol"] == "lineage" and orc["trained_protocol"] == "paper"
    assert len(trainer.calls) == 1 and trainer.calls[0][0] == "tsrm"
    log = [json.loads(line) for line in (out / "run" / "log.jsonl").read_text().splitlines() if line.strip()]
    assert [r["update"] for r in log if "update" in r][-1] == TINY.sizes.train.updates == 2  # trained for real
    assert json.loads((out / "steps" / "train" / "DONE").read_text())["update"] == 2
    ckpts = sorted(p.name for p in (out / "run" / "checkpoints").iterdir())
    for name in ("agent", "explorer", "random"):
        m = json.loads((out / "eval" / name / "metrics.json").read_text())
        assert m["detections"] == "learned" and (out / "eval" / name / "trajectories.jsonl").exists()
    # the detector stage trained the learned detector (its steps) and its tables are in every room
    det = json.loads((out / "steps" / "detector" / "DONE").read_text())
    assert det["steps"] == TINY.sizes.detector.steps and det["fingerprint"].startswith("learned-")
    from tsnav.data.detections import read_fingerprint
    from tsnav.data.reader import list_scenes

    assert {read_fingerprint(p, "learned") for p in list_scenes(out / "world")} == {det["fingerprint"]}
    assert trainer.detections == ["learned"]
    assert json.loads((out / "eval" / "agent" / "metrics.json").read_text())["run"] == str((out / "run").resolve())
    assert (out / "pretrain" / "demae" / "recon.png").exists()
    html = (out / "report" / "index.html").read_text()
    for word in ("agent (TSRM, DE-MAE)", "scripted explorer", "Training", "Pretraining", "Episode gallery"):
        assert word in html
    text = capsys.readouterr().out
    assert "[1/10] world" in text and "[10/10] report" in text and "results on the test episodes" in text
    assert "[9/10] shipped: the agent that ships with tsnav: not on the tiny world" in text
    assert "[4/10] detector" in text and "detections: detections_learned on" in text and "reach of 0.7" in text
    assert "scripted explorer" in text.split("results on the test episodes")[1]
    assert "protocol: paper" in text and "protocol: lineage" in text and "agent trained under paper" in text

    # a second run reuses every stage and trains nothing
    again = CountedTrainer()
    res2 = run_demo(out, TINY, train_fn=again)
    assert [res2["steps"][s][0] for s in STEPS] == ["-" if s == "shipped" else "reused" for s in STEPS]
    assert again.calls == [] and res2["results"] == res["results"]
    assert sorted(p.name for p in (out / "run" / "checkpoints").iterdir()) == ckpts

    # a lost evaluation is redone, and the report after it
    shutil.rmtree(out / "eval" / "random")
    res3 = run_demo(out, TINY, train_fn=again)
    st = {s: res3["steps"][s][0] for s in STEPS}
    assert st["train"] == "reused" and st["evaluate"] == "done" and st["report"] == "done"
    assert (out / "eval" / "random" / "metrics.json").exists()


def test_demo_with_the_real_trainer_prints_the_same_table_twice(tmp_path, tiny_world, capsys):
    """The demo's training budget is in updates: two runs from scratch with the same seed give the same agent
    (weights) and print the same results table, however long each took."""
    from tsnav.checkpoint import weights_digest
    from tsnav.rl.checkpoint import load_model

    cfg = replace(TINY, scale=TINY.sizes.override(train=dict(updates=3, minutes=None, milestone_every=1)))
    tables, digests, detectors = [], [], []
    for k in range(2):
        out = tmp_path / f"demo{k}"
        shutil.copytree(tiny_world, out / "world", ignore=NO_LEARNED)
        capsys.readouterr()
        res = run_demo(out, cfg)
        text = capsys.readouterr().out
        tables.append(text.split("results on the test episodes")[1].split("report:")[0])
        digests.append(weights_digest(load_model(out / "run")[0].state_dict()))
        assert res["results"]["paper"]["agent (TSRM, DE-MAE)"]["ALL"]["episodes"] > 0
        marker = json.loads((out / "steps" / "train" / "DONE").read_text())
        assert marker["update"] == 3
        # the milestones of updates 1-3 were scored on the val rooms; the evaluated agent is the one kept as best
        sel = json.loads((out / "run" / "selection.json").read_text())
        assert sorted(v["update"] for v in sel["scores"].values()) == [1, 2, 3]
        assert marker["checkpoint"]["name"] == sel["best"] and marker["checkpoint"]["candidates"] == 3
        best = weights_digest(load_model(out / "run", out / "run" / "best")[0].state_dict())
        assert best == sel["scores"][sel["best"]]["digest"]
        digests.append(best)
        detectors.append(json.loads((out / "steps" / "detector" / "DONE").read_text())["fingerprint"])
    # the same detector (weights and temperature) and so the same tables, trained on one thread
    assert detectors[0] == detectors[1]
    assert digests[:2] == digests[2:]  # the latest and the selected agent of each run
    assert tables[0] == tables[1] and "agent (TSRM, DE-MAE)" in tables[0]


def test_demo_with_oracle_detections_and_existing_tables(tmp_path, tiny_world, capsys):
    """``--detections oracle`` trains no detector and evaluates on the oracle's table; a world whose rooms already
    hold learned tables (written by an experiment) is used as it is: no detector trained."""
    out = tmp_path / "oracle"
    shutil.copytree(tiny_world, out / "world", ignore=NO_LEARNED)
    trainer = CountedTrainer()
    res = run_demo(out, replace(TINY, detections="oracle"), train_fn=trainer)
    assert res["steps"]["detector"][0] == "-" and not (out / "detector").exists()
    assert trainer.detections == ["oracle"]
    assert json.loads((out / "eval" / "agent" / "metrics.json").read_text())["detections"] == "oracle"
    assert list(res["results"]["lineage"]) == ["agent (TSRM, DE-MAE)", "scripted explorer", "random"]
    assert "not used (--detections oracle)" in capsys.readouterr().out

    out2 = tmp_path / "existing"
    shutil.copytree(out / "world", out2 / "world")
    for p in (out2 / "world").iterdir():  # stand-in for another detector's tables: copies named learned
        if (p / "detections_oracle.hdf5").exists():
            shutil.copy(p / "detections_oracle.hdf5", p / "detections_learned.hdf5")
    from tsnav.errors import CommandError

    with pytest.raises(CommandError, match=r"detections_learned.hdf5 was made by another detector \(oracle-"):
        run_demo(out2, TINY, train_fn=CountedTrainer())

    # learned tables of one detector in every room (an experiment's): used as they are
    from tsnav.pipeline.detector_steps import ensure_learned_detections

    from tsnav.data.reader import list_scenes

    for p in list_scenes(out2 / "world"):
        (p / "detections_learned.hdf5").unlink()
    made = ensure_learned_detections(
        out2 / "world", "learned", tmp_path / "exp_detector", TINY.sizes, progress=False, say=lambda m: None
    )
    capsys.readouterr()
    trainer = CountedTrainer()
    run_demo(out2, TINY, train_fn=trainer)
    assert "no detector trained" in capsys.readouterr().out and not (out2 / "detector").exists()
    assert trainer.detections == ["learned"]
    assert json.loads((out2 / "steps" / "detections" / "DONE").read_text())["fingerprint"] == made["fingerprint"]


def test_demo_on_real_rooms_with_the_shipped_detector(tmp_path, tiny_real, capsys):
    """The default path: real rooms at 128x128 and the detector shipped with tsnav (nothing trained for it, as the
    paper's DETR is trained apart from the agent); its tables go into every room and drive the stage switch; the
    shipped agent is evaluated beside the demo's own. A 64-px world with the shipped detector is refused in one
    line before any work."""
    from tsnav.data.detections import read_fingerprint
    from tsnav.data.reader import list_scenes, load_scene
    from tsnav.detect.shipped import shipped_meta
    from tsnav.errors import CommandError

    with pytest.raises(CommandError, match=r"reads 128x128 frames .* the tiny world has 64x64: use --detector train"):
        run_demo(tmp_path / "refused", replace(TINY, detector="shipped"), train_fn=CountedTrainer())
    assert not (tmp_path / "refused").exists()

    out = tmp_path / "real"
    shutil.copytree(tiny_real, out / "world")
    cfg = replace(
        TINY, preset="tiny-real", detector="shipped", train_rooms_per_type=None, tables_beside_pretraining=True
    )
    trainer = CountedTrainer()
    res = run_demo(out, cfg, train_fn=trainer)
    assert [res["steps"][s][0] for s in STEPS] == ["done"] * len(STEPS)
    text = capsys.readouterr().out
    assert "its tables were written during pretraining" in text  # by the background process
    # beside the demo's agent, the agent that ships with tsnav on the same test episodes, under both protocols; the
    # background process wrote its detector's tables and its encoder's features into the test room only, so the
    # step only evaluated
    from tsnav.pipeline.release import agent_folder, default_agent, read_card

    name = default_agent()
    folder, label = agent_folder(name), f"shipped agent ({name})"
    card = read_card(folder)
    assert all(list(rows)[:2] == ["agent (TSRM, DE-MAE)", label] for rows in res["results"].values())
    assert "written into" not in text.split("[9/10] shipped")[1].split("[10/10]")[0]
    for p in list_scenes(out / "world"):
        split = load_scene(p).meta["split"]
        assert (read_fingerprint(p, card["detections"]) == card["detector_fingerprint"]) == (split == "test")
        assert (p / f"features_{card['features']}.hdf5").exists() == (split == "test")
    for protocol, sub in (("paper", ""), ("lineage", "_lineage")):
        m = json.loads((out / "eval" / f"shipped{sub}" / "metrics.json").read_text())
        mine = json.loads((out / "eval" / f"agent{sub}" / "metrics.json").read_text())
        assert (m["run"], m["detections"], m["checkpoint"]) == (str(folder.resolve()), card["detections"], "best")
        assert m["protocol"] == protocol and m["trained_protocol"] == "lineage" and not m["sample"]
        assert m["episodes_file"] == mine["episodes_file"]
        assert m["metrics"] == res["results"][protocol][label]
    assert f"{label}: the agent that ships with tsnav, trained under lineage" in text
    assert "agent (TSRM, DE-MAE): this demo's agent (2 updates, trained under paper)" in text
    html = (out / "report" / "index.html").read_text()
    assert f"{label} [lineage]" in html and html.count("<video") >= 2  # its gallery, with clips
    marker = json.loads((out / "steps" / "detector" / "DONE").read_text())
    assert marker["source"] == "shipped" and marker["fingerprint"] == shipped_meta()["fingerprint"]
    assert not (out / "detector").exists() and trainer.detections == ["learned"]
    assert all(read_fingerprint(p, "learned") == marker["fingerprint"] for p in list_scenes(out / "world"))
    quality = json.loads((out / "steps" / "detections" / "DONE").read_text())["quality"]
    assert quality["reach"] == 1.0  # the val bathroom's three targets all pass C_target
    # the switch fires, so the scripted explorer (Done only after the switch) succeeds on the test bathroom
    assert res["results"]["paper"]["scripted explorer"]["ALL"]["SR"] > 0.5
    capsys.readouterr()
    res2 = run_demo(out, cfg, train_fn=trainer)  # everything reused, the shipped detector's marker included
    assert [res2["steps"][s][0] for s in STEPS] == ["reused"] * len(STEPS) and len(trainer.calls) == 1
    # switching the detector source in the same folder: refused in one line, the tables are kept
    before = {p.name: read_fingerprint(p, "learned") for p in list_scenes(out / "world")}
    with pytest.raises(
        CommandError,
        match=r"holds the shipped detector's detections_learned.hdf5, not from "
        r"--detector train: use another --out",
    ):
        run_demo(out, replace(cfg, detector="train"), train_fn=trainer)
    assert {p.name: read_fingerprint(p, "learned") for p in list_scenes(out / "world")} == before
    # a folder holding another preset's world is refused before any work (the worlds share room names)
    with pytest.raises(CommandError, match=r"holds the 'tiny-real' world, not 'tiny': use another --out"):
        run_demo(out, replace(cfg, preset="tiny", detector="train"), train_fn=trainer)
    assert len(trainer.calls) == 1


def test_default_threads_do_not_depend_on_the_load(monkeypatch):
    """The default thread count of the demo and the experiments is fixed per machine, not the cores that happen
    to be idle: another count trains another agent (seen here: 2 threads on an idle machine and 1 on a busy one
    gave SR 52.0 and 55.0)."""
    import tsnav.pipeline.experiment as experiment

    monkeypatch.setattr(experiment.os, "cpu_count", lambda: 2)
    assert experiment.default_threads() == experiment.DEFAULT_THREADS == 2
    monkeypatch.setattr(experiment.os, "cpu_count", lambda: 1)
    assert experiment.default_threads() == 1
    monkeypatch.setattr(experiment.os, "cpu_count", lambda: 64)
    assert experiment.default_threads() == 2


def test_results_table_has_one_block_per_protocol():
    """The table assembly on hand-made summaries: a header per protocol, the paper block laid out as before."""
    from tsnav.pipeline.demo import results_table
    from tsnav.metrics import METRICS

    def summ(sr, n):
        m = {k: 0.0 for k in METRICS}
        return {"ALL": {**m, "SR": sr, "episodes": n}, "L>=5": {**m, "SR": sr / 2, "episodes": n // 2}}

    results = {
        "paper": {"agent": summ(0.5, 40), "random": summ(0.0, 40)},
        "lineage": {"agent": summ(0.75, 44), "random": summ(0.25, 44)},
    }
    text = results_table(results, "paper")
    blocks = text.split("results on the test episodes")[1:]
    assert len(blocks) == 2
    assert blocks[0].splitlines()[1].startswith("protocol: paper - Done succeeds with the target in view within 1.0 m")
    assert blocks[1].splitlines()[1].startswith("protocol: lineage - ") and "agent trained under paper" in blocks[1]
    paper_rows = [line for line in blocks[0].splitlines()[3:] if line]
    # the row layout of the demo's table before protocols: label, subset, the five metrics, K
    assert paper_rows[0] == "agent   ALL    " + " ".join(f"{v:6.2f}" for v in (50, 0, 0, 0, 0)) + "     40"
    assert paper_rows[1].startswith("agent   L>=5    25.00") and paper_rows[1].endswith("     20")
    assert blocks[1].splitlines()[3].startswith("agent   ALL     75.00")
    assert len(paper_rows) == 4 and "random" in paper_rows[2]


def test_replacing_the_preset_takes_its_sizes():
    """``DemoConfig`` resolves its sizes when read, so ``dataclasses.replace`` with another preset gets that
    preset's budget and table writing (it kept the first preset's before); explicit sizes are kept."""
    from tsnav.pipeline.config import demo_scale
    from tsnav.pipeline.demo import QUICK_DEMO_PRESET

    quick = DemoConfig()
    longer = replace(quick, preset="demo-real")
    assert quick.sizes == demo_scale(QUICK_DEMO_PRESET) and longer.sizes == demo_scale("demo-real")
    assert quick.sizes.train.updates != longer.sizes.train.updates
    assert quick.tables_beside and not longer.tables_beside
    assert replace(TINY, preset="demo-real").sizes == TINY.sizes  # given sizes stay
    assert not replace(quick, tables_beside_pretraining=False).tables_beside


def test_the_shipped_agent_row_is_left_out_where_it_cannot_run(tmp_path, monkeypatch):
    """The shipped agent's row needs 128-px ithor-real rooms: elsewhere, when asked not to, or when no agent ships,
    the step says why in one line; an agent named that does not exist is refused before any work."""
    from tsnav.errors import CommandError
    from tsnav.pipeline import demo, release

    assert demo.shipped_agent(replace(TINY, preset="tiny"))[2].startswith("not on the tiny world")
    assert demo.shipped_agent(replace(TINY, preset="tiny-real", shipped=False))[2] == "left out (--no-shipped)"
    folder, card, why = demo.shipped_agent(replace(TINY, preset="tiny-real"))
    assert why == "" and folder == release.agent_folder(None) and card["name"] == folder.name
    with pytest.raises(CommandError, match="no shipped agent named 'nope'"):
        demo.shipped_agent(replace(TINY, preset="tiny-real", shipped_agent="nope"))
    monkeypatch.setattr(release, "WEIGHTS", tmp_path / "none")  # a copy of tsnav that ships no agent
    assert (
        demo.shipped_agent(replace(TINY, preset="tiny-real"))[2]
        == "no agent ships with this tsnav (tsnav release pack makes one)"
    )
