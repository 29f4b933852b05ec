"""The how-tos of docs/howto/ and the README's quick start, run as a user would follow them, at tiny scale.

A page's code blocks marked ```` ```bash test ```` hold settings (``NAME=value``) and ``tsnav`` / ``python -m``
commands; blocks marked ```` ```json test-file=PATH ```` are files the user writes; ```` ```python test ```` blocks are
Python run as they stand. This test runs the commands in order, in-process through :func:`tsnav.cli.main`, after
replacing the settings the page names "(test: ...)" with tiny values: the commands themselves are the page's.
"""

from __future__ import annotations

import json
import os
import re
import runpy
import shlex
import shutil
import sys
from pathlib import Path

import pytest

from tsnav.cli import main

ROOT = Path(__file__).resolve().parents[2]
HOWTO = ROOT / "docs" / "howto"
BLOCK = re.compile(r"^```(\w+)([^\n]*)\n(.*?)^```", re.S | re.M)
SETTING = re.compile(r"^([A-Z_][A-Z0-9_]*)=(\S+)\s*(#.*)?$")

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_torch_thread")]


def test_blocks(page: Path) -> list[tuple[str, str, str]]:
    """``(language, info after the language, text)`` of every code block marked ``test`` (or ``test-file=``)."""
    out = []
    for lang, info, text in BLOCK.findall(page.read_text()):
        words = info.split()
        if "test" in words or any(w.startswith("test-file=") for w in words):
            out.append((lang, info.strip(), text))
    return out


test_blocks.__test__ = False  # a helper, not a test


def run_page(page: Path, overrides: dict[str, str], cwd: Path, capsys=None, edit_files=None) -> dict[str, str]:
    """Run ``page``'s test blocks in ``cwd`` with the settings in ``overrides``; return the settings used. Every
    override must name a setting of the page, and every line must be a setting, a comment or a command.
    ``edit_files``: file name -> function of its JSON, for a file block whose tiny version needs another field."""
    env: dict[str, str] = {"HOME": str(cwd / "home")}
    seen = set()
    old = Path.cwd()
    os.chdir(cwd)
    try:
        for lang, info, text in test_blocks(page):
            expand = lambda s: re.sub(r"\$(\w+)|\$\{(\w+)\}", lambda m: env[m.group(1) or m.group(2)], s)  # noqa: E731
            if lang == "json":
                path = Path(expand(info.split("test-file=", 1)[1].split()[0]))
                path.parent.mkdir(parents=True, exist_ok=True)
                edit = (edit_files or {}).get(path.name)
                path.write_text(json.dumps(edit(json.loads(text))) if edit else text)
                continue
            if lang == "python":
                exec(compile(text, f"{page.name}:python", "exec"), {"__name__": "__howto__"})
                continue
            assert lang == "bash", f"{page.name}: a test block in {lang}"
            for line in text.replace("\\\n", " ").splitlines():
                line = line.strip()
                if not line or line.startswith("#"):
                    continue
                m = SETTING.match(line)
                if m:
                    name, value = m.group(1), m.group(2)
                    seen.add(name)
                    env[name] = overrides.get(name, expand(value))
                    continue
                argv = shlex.split(expand(line.split(" #")[0]))
                if argv[0] == "tsnav":
                    rc = main(argv[1:])
                elif argv[:2] == ["python", "-m"]:
                    sys_argv = sys.argv
                    sys.argv = argv[2:]
                    try:
                        runpy.run_module(argv[2], run_name="__main__")
                        rc = 0
                    except SystemExit as e:
                        rc = e.code or 0
                    finally:
                        sys.argv = sys_argv
                else:
                    raise AssertionError(f"{page.name}: not a setting or a command: {line}")
                err = capsys.readouterr().err if capsys else ""
                assert rc == 0, f"{page.name}: `{line}` returned {rc}: {err.strip()[-500:]}"
    finally:
        os.chdir(old)
    assert set(overrides) <= seen, f"{page.name}: no settings {sorted(set(overrides) - seen)}"
    return env


def _copy_world(src: Path, dst: Path) -> None:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("detections_*", "features_*"))


def test_train_and_ship(tiny_real, tmp_path, capsys):
    # the world the page builds is tiny-real; a copy of the session's saves building it again (the command skips
    # complete rooms); the page names the recipe relative to the checkout
    _copy_world(tiny_real, tmp_path / "work" / "world")
    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    env = run_page(
        HOWTO / "train-and-ship.md",
        dict(
            PRESET="tiny-real",
            MODEL="vit_micro",
            IMG="32",
            PRETRAIN_STEPS="2",
            UPDATES="2",
            ENVS="4",
            CHUNK="1",
            VAL="6",
        ),
        tmp_path,
        capsys,
    )

    work = tmp_path / env["WORK"]
    folder = work / "agent" / "tsrm-demae-learned7"
    card = json.loads((folder / "card.json").read_text())
    import tsnav
    from tsnav.settings import read_recipe

    assert card["tsnav_version"] == tsnav.__version__ and card["name"] == "tsrm-demae-learned7"
    assert card["world_preset"] == "tiny-real" and card["test_rooms"] == ["FloorPlan424"]
    for split in ("val", "test"):
        assert {(r["protocol"], r["policy"]) for r in card["figures"][split]["rows"]} == {
            (p, pol) for p in ("paper", "lineage") for pol in ("agent", "scripted explorer", "random")
        }
    recipe = read_recipe(folder / "recipe.toml")
    assert recipe["train"]["updates"] == 2 and recipe["pretrain"]["model"] == "vit_micro"
    assert recipe["select"]["per_room_type"] == 6 and recipe["agent"]["blocked_action"] is True


def test_reproduce_table2(tiny_real, tmp_path, capsys):
    """The page runs the committed recipe; here a tiny recipe written from it (the same experiment, rows of one
    seed at a tiny scale) takes its place."""
    from tsnav.settings import dump_recipe, merge, read_recipe

    recipe = merge(
        read_recipe(ROOT / "configs" / "experiments" / "table2-ablation.toml"),
        {
            "experiment": dict(
                seeds=1, rows=["baseline", "tsrm_demae"], select_per_room_type=6, updates_per_job=2, parallel=1
            ),
            "scale": dict(
                feature_batch_size=256,
                test_per_room_type=6,
                val_per_room_type=6,
                resnet_pretrain_steps=2,
                pretrain=dict(model="vit_micro", patch_size=8, img_size=32, steps=2, batch_size=8),
                train=dict(num_envs=4, updates=2, milestone_every=1),
                detector=dict(steps=4, batch_size=8, max_states_per_scene=24),
            ),
        },
    )
    tiny = tmp_path / "table2-tiny.toml"
    tiny.write_text(dump_recipe(recipe))
    _copy_world(tiny_real, tmp_path / "work" / "world")
    env = run_page(HOWTO / "reproduce-table2.md", dict(PRESET="tiny-real", RECIPE=str(tiny)), tmp_path, capsys)

    out = tmp_path / env["WORK"] / "ablation"
    res = json.loads((out / "results.json").read_text())
    assert [r["row"] for r in res["rows"]] == ["baseline", "tsrm_demae"] and res["protocol"] == "lineage"
    assert "paper" in res["other_protocols"] and res["blocked_action"] and res["detections"] == "learned7"
    assert (out / "report" / "index.html").exists()
    assert read_recipe(out / "recipe.toml")["scale"]["train"]["updates"] == 2


def test_import_ai2thor(tiny_world, tmp_path, capsys):
    from thor_standin import write_lineage_scene
    from tsnav.data.reader import list_scenes

    lineage = tmp_path / "lineage"
    for p in list_scenes(tiny_world):
        write_lineage_scene(p, lineage / p.name)
    env = run_page(HOWTO / "import-ai2thor.md", dict(LINEAGE=str(lineage)), tmp_path, capsys)
    data = tmp_path / env["DATA"]
    assert [p.name for p in list_scenes(data)] == [p.name for p in list_scenes(tiny_world)]

    metrics = json.loads((tmp_path / "runs" / "thor_oracle" / "metrics.json").read_text())
    assert metrics["protocol"] == "lineage"


def test_readme_gymnasium(tiny_real, tmp_path, monkeypatch):
    """The README's Gymnasium lines, run in a folder whose out/demo/world is a tiny world with learned tables."""
    from tsnav.detect.shipped import shipped_detector
    from tsnav.pipeline.detector_steps import write_learned_tables

    world = tmp_path / "out" / "demo" / "world"
    _copy_world(tiny_real, world)
    write_learned_tables(world, "learned", shipped_detector(128, "learned4"), progress=False)
    blocks = [t for lang, _, t in test_blocks(ROOT / "README.md") if lang == "python"]
    assert len(blocks) == 1 and len(blocks[0].strip().splitlines()) <= 6
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(blocks[0], "README.md:python", "exec"), ns)
    assert ns["obs"]["rgb"].shape[-1] == 3 and isinstance(float(ns["reward"]), float)
