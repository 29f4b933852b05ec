"""`tsnav convergence` at tiny size (issue 15, items 3-4 prepared): chunks of updates, each checkpoint scored on
validation episodes, the curve PNG and JSON, and a resumed command that continues instead of starting over."""

import json

import pytest

from tsnav.cli import main
from tsnav.pipeline.convergence import chunk_config, plateaued

from conftest import PIXEL_FEATURES as FEATS


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_convergence_curve_resumes(pixel_world, tmp_path, capsys):
    out = tmp_path / "conv"
    args = [
        "convergence",
        "--data",
        str(pixel_world),
        "--features",
        FEATS,
        "--detections",
        "oracle",
        "--out",
        str(out),
        "--chunk",
        "2",
        "--num-envs",
        "4",
        "--val-per-room-type",
        "3",
        "--lr",
        "3e-3",
    ]
    assert main(args + ["--updates", "4"]) == 0
    curve = json.loads((out / "curve.json").read_text())
    assert [p["update"] for p in curve["points"]] == [2, 4]
    assert all(p["env_steps"] == 4 * 30 * p["update"] for p in curve["points"])
    assert (out / "curve.png").stat().st_size > 10_000 and (out / "run" / "best" / "model.safetensors").exists()
    capsys.readouterr()
    assert main(args + ["--updates", "6"]) == 0  # resumed: only the new chunk is trained and scored
    text = capsys.readouterr().out
    assert text.count("ckpt_") == 1 and "update 6:" in text
    assert [p["update"] for p in json.loads((out / "curve.json").read_text())["points"]] == [2, 4, 6]
    assert (
        main(
            [
                "convergence",
                "--data",
                str(tmp_path / "none"),
                "--features",
                FEATS,
                "--detections",
                "oracle",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    # the entropy weight reaches the run's config; a negative one is refused in one line
    assert json.loads((out / "run" / "config.json").read_text())["train"]["entropy_coef"] == 0.01
    capsys.readouterr()
    assert main(args + ["--updates", "6", "--entropy-coef", "-1"]) == 2
    assert "--entropy-coef must be >= 0" in capsys.readouterr().err
    other = tmp_path / "conv_ent"
    assert main([*args[:8], str(other), *args[9:], "--updates", "2", "--entropy-coef", "0.05"]) == 0
    assert json.loads((other / "run" / "config.json").read_text())["train"]["entropy_coef"] == 0.05
    # so does the training episode length (issue 23: 100-action episodes); 0 is refused in one line
    assert json.loads((out / "run" / "config.json").read_text())["train"]["max_steps"] == 30
    longer = tmp_path / "conv_ep100"
    assert main([*args[:8], str(longer), *args[9:], "--updates", "2", "--max-steps", "100"]) == 0
    assert json.loads((longer / "run" / "config.json").read_text())["train"]["max_steps"] == 100
    capsys.readouterr()
    assert main(args + ["--updates", "6", "--max-steps", "0"]) == 2
    assert "--max-steps must be >= 1" in capsys.readouterr().err


def test_plateau_rule():
    pts = [{"SR": s} for s in (0.1, 0.3, 0.5, 0.4, 0.5)]
    assert plateaued(pts, 2) and not plateaued(pts, 3) and not plateaued(pts, None)


def test_a_chunk_keeps_the_runs_lr_schedule():
    """A run trained in chunks (tsnav convergence, tsnav release make) with a learning-rate schedule (issue 47):
    every chunk's configuration has the whole run's horizon, so the chunks continue one schedule and the resume
    check finds the same run; a constant rate is left as it was."""
    from tsnav.rl.config import TrainConfig

    cfg = TrainConfig(data="w", updates=4000, lr=1e-3, lr_schedule="linear", lr_final=1e-4)
    chunks = [chunk_config(cfg, end, 250) for end in (250, 500, 4000)]
    assert [c.updates for c in chunks] == [250, 500, 4000] and {c.lr_horizon for c in chunks} == {4000}
    assert {c.lr_at(1000) for c in chunks} == {cfg.lr_at(1000)} and len({str(c.identity()) for c in chunks}) == 1
    plain = chunk_config(TrainConfig(data="w", updates=4000), 250, 250)
    assert plain.lr_decay_updates is None and plain.lr_horizon is None and plain.milestone_every == 250
