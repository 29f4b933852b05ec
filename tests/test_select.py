"""`tsnav select` (issue 15): every kept checkpoint of a run scored greedily on validation episodes, the best
kept as RUN/best and used by `tsnav eval --run` unless told otherwise; resumable and atomic."""

import json

import pytest

from tsnav.checkpoint import weights_digest
from tsnav.cli import main
from tsnav.eval.select import select_checkpoint
from tsnav.rl.checkpoint import list_checkpoints, load_model, resolve_checkpoint

from conftest import PIXEL_FEATURES as FEATS


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_select_best_checkpoint_and_eval_uses_it(pixel_world, tmp_path, capsys):
    world, run = pixel_world, tmp_path / "run"
    assert main(["train", "--data", str(world), "--features", FEATS, "--detections", "oracle", "--algo", "batched",
                 "--out", str(run),
                 "--updates", "6", "--num-envs", "4", "--preset", "cpu", "--rollout-steps", "5", "--checkpoint-every",
                 "1", "--milestone-every", "2", "--lr", "3e-3", "--quiet"]) == 0
    names = [p.name for p in list_checkpoints(run)]
    assert names == ["ckpt_000000002", "ckpt_000000004", "ckpt_000000005", "ckpt_000000006"]
    eps = tmp_path / "val.json"
    assert main(["episodes", "--data", str(world), "--split", "val", "--per-room-type", "6", "--out", str(eps)]) == 0
    # no selection yet: auto = latest; best is refused in one line
    assert resolve_checkpoint(run, "auto") is None
    assert main(["eval", "--data", str(world), "--episodes", str(eps), "--run", str(run), "--checkpoint", "best",
                 "--out", str(tmp_path / "e0")]) == 2
    assert "no best checkpoint" in capsys.readouterr().err

    seen = []
    res = select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)
    assert sorted(res["scores"]) == names and len(seen) == 4
    rank = {k: (v["metrics"]["ALL"]["SR"], v["metrics"]["ALL"]["SPL"], -v["update"]) for k, v in res["scores"].items()}
    assert res["best"] == max(rank, key=rank.get)
    best = run / "best"
    assert weights_digest(load_model(run, best)[0].state_dict()) == res["scores"][res["best"]]["digest"]
    assert json.loads((run / "selection.json").read_text())["best"] == res["best"]
    # resumed: nothing is scored again; a broken score file is recomputed, not trusted
    seen.clear()
    assert select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)["best"] == res["best"]
    assert seen == []
    (run / "selection.json").write_text('{"scores": {tru')
    assert select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)["best"] == res["best"]
    assert len(seen) == 4

    # `tsnav eval --run` evaluates best by default, the same as naming the chosen checkpoint's folder
    out = {}
    for tag, extra in (("auto", []), ("path", ["--checkpoint", str(run / "checkpoints" / res["best"])]),
                       ("latest", ["--checkpoint", "latest"])):
        assert main(["eval", "--data", str(world), "--episodes", str(eps), "--run", str(run), "--max-steps", "30",
                     "--out", str(tmp_path / tag), *extra]) == 0
        out[tag] = json.loads((tmp_path / tag / "records.jsonl").read_text().splitlines()[0])
    assert out["auto"] == out["path"]
    assert json.loads((tmp_path / "auto" / "metrics.json").read_text())["checkpoint"] == "auto"
    assert main(["select", "--run", str(run), "--data", str(world), "--episodes", str(eps), "--max-steps", "30"]) == 0
    assert f"best checkpoint {res['best']}" in capsys.readouterr().out
    assert main(["select", "--run", str(tmp_path / "none"), "--data", str(world), "--episodes", str(eps)]) == 2
