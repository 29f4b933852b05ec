"""`tsnav select` (issue 15): every kept checkpoint of a run scored greedily on validation episodes, the best
kept as RUN/best and used by `tsnav eval --run` unless told otherwise; resumable and atomic."""

import json
import os

import pytest

from rl_helpers import train_argv
from tsnav.checkpoint import weights_digest
from tsnav.cli import main
from tsnav.eval import select as sel
from tsnav.eval.runner import eval_bank, eval_policy
from tsnav.eval.select import select_checkpoint
from tsnav.rl.checkpoint import BEST, list_checkpoints, load_model, resolve_checkpoint
from tsnav.sim.episodes import read_episodes

from conftest import PIXEL_FEATURES as FEATS


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_select_best_checkpoint_and_eval_uses_it(pixel_world, tmp_path, capsys, monkeypatch):
    world, run = pixel_world, tmp_path / "run"
    assert (
        main(
            train_argv(
                str(world),
                str(run),
                FEATS,
                "--updates",
                "6",
                "--checkpoint-every",
                "1",
                "--milestone-every",
                "2",
                "--lr",
                "3e-3",
            )
        )
        == 0
    )
    names = [p.name for p in list_checkpoints(run)]
    assert names == ["ckpt_000000002", "ckpt_000000004", "ckpt_000000005", "ckpt_000000006"]
    eps = tmp_path / "val.json"
    assert main(["episodes", "--data", str(world), "--split", "val", "--per-room-type", "6", "--out", str(eps)]) == 0
    # no selection yet: auto = latest; best is refused in one line
    assert resolve_checkpoint(run, "auto") is None
    assert (
        main(
            [
                "eval",
                "--data",
                str(world),
                "--episodes",
                str(eps),
                "--run",
                str(run),
                "--checkpoint",
                "best",
                "--out",
                str(tmp_path / "e0"),
            ]
        )
        == 2
    )
    assert "no best checkpoint" in capsys.readouterr().err

    seen = []
    res = select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)
    assert sorted(res["scores"]) == names and len(seen) == 4
    rank = {k: (v["metrics"]["ALL"]["SR"], v["metrics"]["ALL"]["SPL"], -v["update"]) for k, v in res["scores"].items()}
    assert res["best"] == max(rank, key=rank.get)
    best = run / "best"
    assert weights_digest(load_model(run, best)[0].state_dict()) == res["scores"][res["best"]]["digest"]
    assert json.loads((run / "selection.json").read_text())["best"] == res["best"]
    # resumed: nothing is scored again, nor reloaded and rehashed (weights files unchanged: same size and
    # modification time); a broken score file is recomputed, not trusted
    hashed = []
    digest = sel._digest
    monkeypatch.setattr(sel, "_digest", lambda run_dir, ck: hashed.append(ck.name) or digest(run_dir, ck))
    seen.clear()
    assert select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)["best"] == res["best"]
    assert seen == [] and hashed == []
    (run / "selection.json").write_text('{"scores": {tru')
    assert select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)["best"] == res["best"]
    assert len(seen) == 4 and sorted(hashed) == sorted(names + [BEST])  # RUN/best checked again too
    # a checkpoint whose weights file was touched is rehashed (only it), not rescored: its weights are the same
    f = run / "checkpoints" / names[0] / "model.safetensors"
    os.utime(f, ns=(f.stat().st_atime_ns, f.stat().st_mtime_ns + 10**9))
    seen.clear(), hashed.clear()
    select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)
    assert seen == [] and hashed == [names[0]]

    # `tsnav eval --run` evaluates best by default, the same as naming the chosen checkpoint's folder, and not
    # the latest: the weights of the policy each evaluation folder describes (what evaluate_to_folder ran and a
    # re-roll loads) are compared. Tiny training scores every checkpoint alike, so the earliest wins the tie and
    # best differs from latest; the records of such near-identical agents can coincide, the weights cannot.
    assert res["best"] != names[-1], "the test needs a best checkpoint other than the latest"
    digests = {}
    for tag, extra in (
        ("auto", []),
        ("path", ["--checkpoint", str(run / "checkpoints" / res["best"])]),
        ("latest", ["--checkpoint", "latest"]),
    ):
        assert (
            main(
                [
                    "eval",
                    "--data",
                    str(world),
                    "--episodes",
                    str(eps),
                    "--run",
                    str(run),
                    "--max-steps",
                    "30",
                    "--out",
                    str(tmp_path / tag),
                    *extra,
                ]
            )
            == 0
        )
        meta = json.loads((tmp_path / tag / "metrics.json").read_text())
        episodes, _ = read_episodes(eps)
        digests[tag] = weights_digest(eval_policy(meta, eval_bank(meta, episodes)).model.state_dict())
    assert digests["auto"] == digests["path"] == res["scores"][res["best"]]["digest"]
    assert digests["latest"] == res["scores"][names[-1]]["digest"] != digests["auto"]
    assert (tmp_path / "auto" / "records.jsonl").read_bytes() == (tmp_path / "path" / "records.jsonl").read_bytes()
    assert json.loads((tmp_path / "auto" / "metrics.json").read_text())["checkpoint"] == "auto"
    # a checkpoint whose weights changed (here: another one's file copied over it) is rehashed and rescored
    (run / "checkpoints" / names[1] / "model.safetensors").write_bytes(
        (run / "checkpoints" / names[2] / "model.safetensors").read_bytes()
    )
    seen.clear(), hashed.clear()
    res2 = select_checkpoint(run, world, eps, max_steps=30, progress=seen.append)
    assert len(seen) == 1 and seen[0].strip().startswith(names[1]) and hashed[0] == names[1]
    assert res2["scores"][names[1]]["digest"] == res["scores"][names[2]]["digest"]
    assert main(["select", "--run", str(run), "--data", str(world), "--episodes", str(eps), "--max-steps", "30"]) == 0
    assert f"best checkpoint {res['best']}" in capsys.readouterr().out
    assert main(["select", "--run", str(tmp_path / "none"), "--data", str(world), "--episodes", str(eps)]) == 2
