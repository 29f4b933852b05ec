"""The shipped agent (issue 23 section 4): `tsnav release pack` makes a folder from a training run and its
encoder; `tsnav release eval` builds the test rooms it names, the shipped detector's tables and the float16
encoder's features, and evaluates it; the float16 encoder stays within rounding of the float32 one; bad input gets
one-line errors."""

import json
import shutil

import numpy as np
import pytest
import torch

from tsnav.cli import main
from tsnav.data.reader import list_scenes, load_scene
from tsnav.pipeline import release

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TRAIN_ROOM, TEST_ROOM = "FloorPlan408", "FloorPlan424"  # the tiny-real preset's train and test bathrooms


@pytest.fixture(scope="module")
def packed(tiny_real, tmp_path_factory):
    """A tiny agent trained two updates on one real room with a 2-step DE-MAE encoder, packed."""
    from tsnav.detect.shipped import shipped_meta
    from tsnav.pipeline.steps import EncoderSpec, ensure_encoder, ensure_features
    from tsnav.pipeline.detector_steps import write_learned_tables
    from tsnav.detect.shipped import shipped_detector

    root = tmp_path_factory.mktemp("release")
    data = root / "world"
    data.mkdir()
    shutil.copytree(tiny_real / TRAIN_ROOM, data / TRAIN_ROOM)
    pre = dict(method="demae", model="vit_micro", patch_size=16, img_size=32, steps=2, batch_size=4, device="cpu")
    es = EncoderSpec("demae", str(root / "pre"), "vit_micro", 16, 32, pre)
    ensure_encoder(es, data)
    feats = ensure_features(es, data, ["train"], batch_size=64)
    write_learned_tables(data, "learned4", shipped_detector(128, "learned4"), progress=False)
    run = root / "run"
    assert (
        main(
            [
                "train",
                "--out",
                str(run),
                "--data",
                str(data),
                "--features",
                feats,
                "--reward",
                "tsrm",
                "--algo",
                "batched",
                "--num-envs",
                "4",
                "--preset",
                "cpu",
                "--detections",
                "learned4",
                "--updates",
                "2",
                "--quiet",
            ]
        )
        == 0
    )
    ck = sorted((run / "checkpoints").iterdir())[-1]
    card = {
        "name": "tiny",
        "summary": "a test agent",
        "world_preset": "ithor-real",
        "world_version": 1,
        "image_size": 128,
        "test_rooms": [TEST_ROOM],
        "detector_shipped": "learned4",
        "detector_fingerprint": shipped_meta("learned4")["fingerprint"],
        "detections": "learned4",
        "protocol": "paper",
        "budget": "2 updates",
        "figures": {},
    }
    (root / "card.json").write_text(json.dumps(card))
    out = root / "agent"
    assert (
        main(
            [
                "release",
                "pack",
                "--run",
                str(run),
                "--checkpoint",
                str(ck),
                "--encoder-run",
                str(root / "pre"),
                "--card",
                str(root / "card.json"),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    return {"root": root, "data": data, "run": run, "out": out, "ck": ck, "feats": feats}


def test_pack_writes_a_loadable_agent_folder(packed):
    out = packed["out"]
    card = release.read_card(out)
    assert card["features"] != packed["feats"] and card["features"].startswith("demae-")
    assert json.loads((out / "config.json").read_text())["train"]["features"] == card["features"]
    assert not (out / "best" / "optimizer.safetensors").exists()
    assert card["policy_update"] == json.loads((packed["ck"] / "state.json").read_text())["progress"]["update"] == 2
    assert "tsnav release eval" in (out / "card.md").read_text()
    # the card records the tsnav version that packed it (one source: tsnav.__version__, also pyproject's)
    import tsnav

    assert card["tsnav_version"] == tsnav.__version__ and f"tsnav {tsnav.__version__}" in (out / "card.md").read_text()
    # the policy weights are the checkpoint's, byte for byte
    assert (out / "best" / "model.safetensors").read_bytes() == (packed["ck"] / "model.safetensors").read_bytes()
    # the encoder is stored in float16 and loads into float32
    from tsnav.checkpoint import load_tensors

    sd, meta = load_tensors(out / "encoder.safetensors")
    assert {v.dtype for v in sd.values() if v.is_floating_point()} == {torch.float16}
    assert meta["stored_dtype"] == "float16"
    assert release.agent_folder(str(out)) == out
    # packed again from a packed agent (as tsrm-demae-paper-protocol from learned7's encoder): the same file
    release.pack_encoder(out / "encoder.safetensors", packed["root"] / "again.safetensors")
    assert (packed["root"] / "again.safetensors").read_bytes() == (out / "encoder.safetensors").read_bytes()


def test_float16_encoder_features_match_float32(packed, tiny_real):
    from tsnav.pretrain.features import load_encoder, scene_features

    full = load_encoder(str(packed["root"] / "pre"))
    half = load_encoder(str(packed["out"] / "encoder.safetensors"))
    assert {p.dtype for p in half.module.parameters()} == {torch.float32}
    scene = load_scene(packed["data"] / TRAIN_ROOM)
    keys = scene.keys[:64]
    a = scene_features(full, scene.path, keys).astype(np.float32)
    b = scene_features(half, scene.path, keys).astype(np.float32)
    scale = np.abs(a).max()
    # rounding the weights to float16 moves the features by far less than their own spread
    assert np.abs(a - b).max() < 0.02 * scale
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.999


def test_release_eval_builds_what_it_needs_and_prints_the_table(packed, capsys):
    world, ev = packed["root"] / "test_world", packed["root"] / "eval"
    args = [
        "release",
        "eval",
        "--agent",
        str(packed["out"]),
        "--data",
        str(world),
        "--out",
        str(ev),
        "--workers",
        "1",
        "--threads",
        "1",
    ]
    # a --data folder that does not exist is refused in one line unless the user asks to build there
    assert main(args) == 2
    assert f"--data {world}: no such world folder (--build-world builds" in capsys.readouterr().err
    assert not world.exists()
    assert main(args + ["--build-world"]) == 0
    text = capsys.readouterr().out
    assert [p.name for p in list_scenes(world)] == [TEST_ROOM]
    card = release.read_card(packed["out"])
    assert (world / TEST_ROOM / f"features_{card['features']}.hdf5").exists()
    assert (world / TEST_ROOM / "detections_learned4.hdf5").exists()
    res = json.loads((ev / "results.json").read_text())
    assert [(r["protocol"], r["policy"]) for r in res["rows"]] == [
        (p, pol) for p in ("paper", "lineage") for pol in ("agent", "scripted explorer", "random")
    ]
    by = {(r["protocol"], r["policy"]): r for r in res["rows"]}
    # each protocol has its own list, recorded as such, and the table names the cross-protocol evaluation
    eps = {p: json.loads((ev / f"episodes_test_{p}.json").read_text()) for p in ("paper", "lineage")}
    assert eps["lineage"]["protocol"] == "lineage" and eps["paper"]["protocol"] == "paper"
    assert by[("lineage", "agent")]["episodes"] == len(eps["lineage"]["episodes"])
    assert "protocol: lineage (agent trained under paper)" in text
    assert all(0.0 <= r["metrics"]["ALL"]["SR"] <= 1.0 and r["episodes"] > 0 for r in res["rows"])
    assert "scripted explorer" in text and "SSSPL" in text
    assert res["inputs"] == release.release_inputs(packed["out"], card, world, ev, ["paper", "lineage"], True, "test")
    # a second run with nothing changed prints the saved table, says so in one line and evaluates nothing
    # (and, asked to, writes the figures into the card)
    before = (ev / "results.json").read_bytes()
    stamps = {p: p.stat().st_mtime_ns for p in ev.rglob("metrics.json")}
    assert main(args + ["--update-card"]) == 0
    second = capsys.readouterr().out
    assert "[release] nothing changed since the evaluation of" in second and "--force evaluates again" in second
    assert (ev / "results.json").read_bytes() == before and stamps == {p: p.stat().st_mtime_ns for p in stamps}
    assert (
        second.split("real test rooms")[1].split("\n", 1)[1].replace("read ", "wrote ")
        == text.split("real test rooms")[1].split("\n", 1)[1]
    )  # the same table, line for line
    # --force evaluates again: the same figures
    assert main(args + ["--force"]) == 0
    forced = capsys.readouterr().out
    assert "nothing changed" not in forced and "steps: world" in forced
    again = json.loads((ev / "results.json").read_text())
    assert [r["metrics"] for r in again["rows"]] == [r["metrics"] for r in res["rows"]]
    assert "built" not in forced
    card = release.read_card(packed["out"])
    assert card["figures"]["test"]["rows"] == again["rows"]
    sr = 100 * again["rows"][0]["metrics"]["ALL"]["SR"]
    assert f"| paper | agent | ALL | {sr:.2f} |" in (packed["out"] / "card.md").read_text()
    # an agent of another rules version never reuses these rooms, nor a list drawn on another world: one line each
    from tsnav.errors import CommandError

    with pytest.raises(CommandError, match=r"another ithor-real rules version than this agent's \(version 2\)"):
        release.ensure_test_world(world, {**card, "world_version": 2}, 1)
    with pytest.raises(CommandError, match="was drawn on .* not on .*elsewhere"):
        release.release_episodes(packed["root"] / "elsewhere", ev, "paper")
    assert release.release_episodes(world, ev, "paper") == ev / "episodes_test_paper.json"

    # what "nothing changed" means: each of these changes the record, so the next run evaluates again
    import h5py

    from tsnav.checkpoint import load_tensors, save_tensors

    def inputs(folder=packed["out"], protocols=("paper", "lineage"), baselines=True):
        return release.release_inputs(folder, card, world, ev, list(protocols), baselines, "test")

    base = inputs()
    assert base == json.loads((ev / "results.json").read_text())["inputs"]
    assert inputs(protocols=["lineage"]) != base and inputs(baselines=False) != base
    graph = world / TEST_ROOM / "graph.json"
    keep = graph.read_bytes()
    graph.write_bytes(keep + b" ")  # the room's state graph rewritten
    assert inputs()["data"]["rooms"] != base["data"]["rooms"]
    graph.write_bytes(keep)
    with h5py.File(world / TEST_ROOM / "detections_learned4.hdf5", "r+") as f:  # a table of another detector
        fp = f.attrs["fingerprint"]
        f.attrs["fingerprint"] = "learned-0000"
    assert inputs()["data"]["rooms"][TEST_ROOM]["detections"] == "learned-0000"
    with h5py.File(world / TEST_ROOM / "detections_learned4.hdf5", "r+") as f:
        f.attrs["fingerprint"] = fp
    other = packed["root"] / "other" / packed["out"].name  # the same agent with other policy weights
    shutil.copytree(packed["out"], other)
    sd, meta = load_tensors(other / "best" / "model.safetensors")
    name = sorted(sd)[0]
    sd[name] = sd[name] + 1e-3
    save_tensors(other / "best" / "model.safetensors", sd, meta)
    changed = inputs(other)
    assert (
        changed["agent"]["policy"] != base["agent"]["policy"]
        and changed["agent"]["encoder"] == base["agent"]["encoder"]
    )
    assert inputs() == base
    (ev / "episodes_test_lineage.json").rename(ev / "moved.json")  # a missing input: the evaluation must run
    assert inputs() is None and release.saved_results(ev, None) is None
    (ev / "moved.json").rename(ev / "episodes_test_lineage.json")
    assert release.saved_results(ev, base)["rows"] == again["rows"]


def test_release_folders_by_version_agent_and_split():
    from pathlib import Path

    assert release.release_folders({"world_version": 2}, "a", "test") == (
        Path("out/release/world-v2"),
        Path("out/release/eval/a/test"),
    )
    assert release.release_folders({}, "a", "val") == (Path("out/release/world-v1"), Path("out/release/eval/a/val"))
    assert release.release_folders({"world_version": 2}, "a", "test", "W", "E") == (Path("W"), Path("E"))


def test_one_line_errors(packed, tmp_path, capsys):
    assert main(["release", "eval", "--agent", "no-such-agent", "--data", str(tmp_path / "w")]) == 2
    assert "no shipped agent named 'no-such-agent'" in capsys.readouterr().err
    broken = tmp_path / "broken"
    shutil.copytree(packed["out"], broken)
    (broken / "encoder.safetensors").unlink()
    assert main(["release", "eval", "--agent", str(broken), "--data", str(tmp_path / "w")]) == 2
    assert "not a complete shipped agent (no encoder.safetensors)" in capsys.readouterr().err
    # packing over an existing folder is refused, and the folder is untouched
    before = (packed["out"] / "card.json").read_bytes()
    assert (
        main(
            [
                "release",
                "pack",
                "--run",
                str(packed["run"]),
                "--encoder-run",
                str(packed["root"] / "pre"),
                "--card",
                str(packed["root"] / "card.json"),
                "--out",
                str(packed["out"]),
            ]
        )
        == 2
    )
    assert "exists" in capsys.readouterr().err and (packed["out"] / "card.json").read_bytes() == before
    bad = tmp_path / "card.json"
    bad.write_text('{"name": "x"}')
    assert (
        main(
            [
                "release",
                "pack",
                "--run",
                str(packed["run"]),
                "--encoder-run",
                str(packed["root"] / "pre"),
                "--card",
                str(bad),
                "--out",
                str(tmp_path / "new"),
            ]
        )
        == 2
    )
    assert "missing fields" in capsys.readouterr().err and not (tmp_path / "new").exists()


def test_one_shipped_agent_is_the_default(capsys):
    agents = release.shipped_agents()
    marked = [n for n, p in agents.items() if release.read_card(p).get("default")]
    assert marked == [release.default_agent()] == ["tsrm-demae-learned7"]
    # `tsnav release list`: each agent, the default marked, and its cards' test figures in one line
    assert main(["release", "list"]) == 0
    out = capsys.readouterr().out
    assert (
        "tsrm-demae-learned7 (default):" in out and "tsrm-demae-learned6:" in out and "tsrm-demae-learned4-v2:" in out
    )
    assert "lineage 82.20 / 41.72" in out and "lineage 79.80 / 39.56" in out and "lineage 73.00 / 37.11" in out
    assert "detector learned7" in out and "detector learned6" in out
    assert "no test figures" in release.headline({"detector_shipped": "learned4"})


@pytest.mark.parametrize("name", sorted(release.shipped_agents()))
def test_the_shipped_agents_are_whole_and_match_their_cards(name):
    from tsnav.detect.shipped import shipped_meta
    from tsnav.pretrain.features import load_encoder
    from tsnav.rl.checkpoint import load_model

    folder = release.agent_folder(name)
    card = release.read_card(folder)
    assert all(k in card for k in release.CARD_REQUIRED)
    # the detector it was trained with ships too, unchanged
    assert shipped_meta(card["detector_shipped"])["fingerprint"] == card["detector_fingerprint"]
    enc = load_encoder(str(folder / "encoder.safetensors"))
    assert enc.fingerprint == card["encoder_fingerprint"] and card["features"].endswith(enc.fingerprint[:10])
    model, state = load_model(folder, folder / "best")
    assert model.feature_shape == (enc.config["embed_dim"], 4, 4)
    # figures of its evaluation split (test; a RoboTHOR agent's val) under both protocols, agent first, as the
    # README's headline
    split = release.eval_split(card)
    rows = card["figures"][split]["rows"]
    assert {r["protocol"] for r in rows} == {"paper", "lineage"} and rows[0]["policy"] == "agent"
    # val and test; a RoboTHOR agent's val scenes only (they are its benchmark)
    assert (folder / "card.md").read_text().count("| lineage | agent | ALL |") == (2 if split == "test" else 1)
    size = sum(f.stat().st_size for f in folder.rglob("*") if f.is_file())
    assert size < 20e6


def test_release_starts_without_torch():
    """`tsnav release list` and a release evaluation that prints its saved table need no torch: the module imports
    it only where tensors are read or written (torch's import is most of a second call's time)."""
    import subprocess
    import sys

    code = "import sys, tsnav.pipeline.release; print('torch' in sys.modules)"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert res.stdout.strip() == "False"
