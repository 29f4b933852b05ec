"""Settings from one source (tsnav.settings) and recipe files (configs/): options generated from the config
dataclasses, recipes read, written and applied, the project's recipe files equal to the commands and shipped
configs they stand for, resumes with other settings refused, abbreviations refused, bugs keep their traceback."""

import argparse
import json
import shlex
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

from tsnav import cli
from tsnav.agent.model import AgentConfig
from tsnav.cli import main
from tsnav.errors import CommandError
from tsnav.rl.config import BUDGET_FIELDS, TrainConfig
from tsnav.rl.recipe import identity_recipe, resolve_run
from tsnav.settings import (
    apply_sets,
    build,
    dump_recipe,
    field_docs,
    first_difference,
    parse_value,
    read_recipe,
    to_recipe,
)
from tsnav.tsrm.reward import RewardConfig

from conftest import PIXEL_FEATURES as FEATS

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
WEIGHTS = ROOT / "src" / "tsnav" / "agent" / "weights"


def command_line(path: Path) -> list[str]:
    """The ``# command:`` line of a recipe file, as arguments after ``tsnav``."""
    line = next(x for x in path.read_text().splitlines() if x.startswith("# command: "))
    return shlex.split(line.removeprefix("# command: "))[1:]


def parse(command: str, argv: list[str]) -> argparse.Namespace:
    import importlib

    p = cli.new_parser(prog=f"tsnav {command}")
    importlib.import_module(cli.COMMANDS[command][0]).build_parser(p)
    return p.parse_args(argv)


# -- settings --------------------------------------------------------------------------------------------------


def test_field_docs_are_the_help():
    docs = field_docs(TrainConfig)
    assert set(docs) >= {f.name for f in fields(TrainConfig)}
    assert docs["lr"].startswith("Adam learning rate") and "``" not in docs["detections"]
    assert field_docs(RewardConfig)["k_distance"].startswith("K_d")
    p = cli.new_parser()
    from tsnav.rl.command import build_parser

    build_parser(p)
    text = p.format_help()
    for option in (
        "--k-explore",
        "--k-distance",
        "--collision-penalty",
        "--slack",
        "--success-reward",
        "--near-level",
        "--far-level",
        "--near-down",
        "--far-down",
        "--c-target",
        "--dropout",
        "--blocked-action",
        "--entropy-coef",
        "--ranks",
        "--lr",
    ):
        assert option in text, option
    assert "Adam learning rate" in text and "K_d, reward per pose-graph action" in text


def test_recipe_round_trip_and_sets():
    recipe = {
        "train": {"lr": 1e-3, "episodes": None, "mirror": True, "data": "x"},
        "reward": {"area": {"far_level": 5.0}},
        "agent": {"dropout": 0.3},
    }
    text = dump_recipe(recipe, header="a recipe")
    assert text.startswith("# a recipe") and 'episodes = "none"' in text
    again = read_recipe_text(text)
    assert again["train"]["episodes"] == "none" and again["reward"]["area"]["far_level"] == 5.0
    cfg, agent = resolve_run(again)
    assert cfg.episodes is None and cfg.lr == 1e-3 and cfg.mirror and agent.dropout == 0.3
    assert cfg.reward_config().area.far_level == 5.0 and cfg.reward_settings == {"area": {"far_level": 5.0}}
    s = apply_sets(again, ["reward.k_distance=0.3", "train.detections=none", "agent.blocked_action=true"])
    cfg, agent = resolve_run(s)
    assert cfg.reward_config().k_distance == 0.3 and cfg.detections is None and agent.blocked_action
    assert parse_value("1e-3") == 1e-3 and parse_value("learned7") == "learned7" and parse_value("[1, 2]") == [1, 2]
    for bad, words in ((["lr=1"], "SECTION.KEY=VALUE"), (["nosection.lr=1"], "no section 'nosection'")):
        with pytest.raises(CommandError, match=words):
            apply_sets({}, bad, ("train", "reward", "agent"))
    with pytest.raises(CommandError, match=r"\[train\]: no setting lrr"):
        resolve_run({"train": {"lrr": 1}})
    with pytest.raises(CommandError, match=r"train.lr: 'fast' is not a float"):
        resolve_run({"train": {"lr": "fast"}})
    with pytest.raises(CommandError, match=r"--max-steps must be >= 1, got 0 \(recipe: train.max_steps\)"):
        resolve_run({"train": {"max_steps": 0}})
    with pytest.raises(CommandError, match="train.reward"):
        resolve_run({"reward": {"variant": "baseline"}})


def read_recipe_text(text: str) -> dict:
    import tomllib

    return tomllib.loads(text)


def test_first_difference_names_the_setting():
    a = identity_recipe(TrainConfig(), AgentConfig())
    b = identity_recipe(TrainConfig(reward_settings={"k_distance": 0.3}), AgentConfig())
    assert first_difference(a, b) == ("reward.k_distance", 0.15, 0.3)
    assert first_difference(a, identity_recipe(TrainConfig(updates=5), AgentConfig())) is None  # the budget
    assert TrainConfig(reward_settings={"k_distance": 0.15}).reward_settings == {}  # canonical


def test_options_are_refused_abbreviated(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--out", "x", "--quie"])
    assert "unrecognized arguments: --quie" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["release", "eval", "--agen", "x"])


def test_bugs_keep_their_traceback(monkeypatch, capsys):
    import tsnav.report.claims as claims
    from tsnav.protocol import check_protocol

    def bug(args):
        return np.zeros(2).reshape(3)  # numpy's ValueError: a bug, not the user's mistake

    def checked(args):
        check_protocol("bogus")  # tsnav's own check (a raise statement of tsnav): one line

    monkeypatch.setattr(claims, "run", bug)
    with pytest.raises(ValueError, match="reshape"):
        main(["claims", "x"])
    monkeypatch.setattr(claims, "run", checked)
    assert main(["claims", "x"]) == 2
    assert capsys.readouterr().err.strip().startswith("tsnav claims: error: unknown success protocol 'bogus'")
    with pytest.raises(ValueError):
        main(["--debug", "claims", "x"])


# -- the project's recipe files ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["table2-ablation", "table3-pretraining", "fig4-threshold"])
def test_experiment_recipes_equal_their_commands(name):
    from tsnav.pipeline.experiment import resolve
    from tsnav.pipeline.recipes import experiment_recipe

    path = CONFIGS / "experiments" / f"{name}.toml"
    argv = command_line(path)
    a = resolve(parse("experiment", argv[1:] + ["--print-recipe"]))
    b = resolve(parse("experiment", [str(path), "--print-recipe"]))
    assert experiment_recipe(*a, paths=False) == experiment_recipe(*b, paths=False)
    # and the recipe file is the resolved recipe, written out
    assert read_recipe(path) == read_recipe_text(dump_recipe(experiment_recipe(*a, paths=False)))


def test_demo_recipe_equals_the_demo():
    from tsnav.pipeline.demo import demo_recipe, resolve

    path = CONFIGS / "demo.toml"
    plain = resolve(parse("demo", command_line(path)[1:]))
    recipe = resolve(parse("demo", ["--config", str(path)]))
    assert demo_recipe(plain) == demo_recipe(recipe) and recipe.sizes == plain.sizes
    assert read_recipe(path) == read_recipe_text(dump_recipe(demo_recipe(plain)))


@pytest.mark.parametrize("name", sorted(p.name for p in WEIGHTS.iterdir() if (p / "card.json").exists()))
def test_agent_recipes_equal_the_shipped_configs(name, tmp_path):
    """Every shipped agent has its recipe, configs/agents/NAME.toml, whose [train], [reward] and [agent] are the
    shipped run's config.json, but the budget, the data and the features (the work folder's)."""
    from tsnav.pipeline.agent_recipe import resolve_agent
    from tsnav.rl.train import stored_config

    path = CONFIGS / "agents" / f"{name}.toml"
    r = resolve_agent(read_recipe(path), tmp_path)
    shipped_cfg, shipped_agent = stored_config(WEIGHTS / name)
    ours = identity_recipe(*r.run)
    theirs = identity_recipe(shipped_cfg, shipped_agent)
    for d in (ours, theirs):
        d["train"].pop("data"), d["train"].pop("features")
    assert first_difference(theirs, ours) is None
    saved = json.loads((WEIGHTS / name / "config.json").read_text())
    reward = to_recipe(r.run[0].reward_config())  # fields added since the run are at the paper's values
    assert saved["reward"] == {k: reward[k] for k in saved["reward"]}
    added = {k: v for k, v in reward.items() if k not in saved["reward"]}
    assert added == {k: to_recipe(RewardConfig())[k] for k in added}  # at their defaults: the paper's reward
    assert not any(str(v).startswith("/") for v in saved["train"].values())  # no machine path ships
    card = json.loads((WEIGHTS / name / "card.json").read_text())
    assert r.detections.card_shipped == card["detector_shipped"] and r.world.version == card["world_version"]
    assert card.get("trained_detector_shipped", card["detector_shipped"]) == r.detections.shipped
    assert saved["train"]["detections"] == r.detections.name  # the shipped run trained on the recipe's tables
    assert r.card.get("default", False) == card.get("default", False)  # one default agent, as its card says


def test_a_recipe_extends_another(tmp_path):
    """``extends`` lays a recipe over another (relative to its own folder; chains too), key by key; a missing or
    circular base, or one that is not a path, is refused in one line naming the file."""
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "a.toml").write_text(
        'name = "a"\n[train]\nlr = 0.001\nseed = 1\n[reward]\nk_distance = 0.15\n[reward.area]\nnear_level = 1.0\nfar_level = 4.0\n'
    )
    (tmp_path / "base" / "b.toml").write_text('extends = "a.toml"\nname = "b"\n[train]\nseed = 2\n')
    (tmp_path / "c.toml").write_text(
        'extends = "base/b.toml"\nname = "c"\n[reward.area]\nnear_level = 0.5\n[card]\nsummary = "c"\n'
    )
    assert read_recipe(tmp_path / "c.toml") == {
        "name": "c",
        "train": {"lr": 0.001, "seed": 2},
        "reward": {"k_distance": 0.15, "area": {"near_level": 0.5, "far_level": 4.0}},
        "card": {"summary": "c"},
    }
    assert read_recipe(tmp_path / "base" / "a.toml")["train"] == {"lr": 0.001, "seed": 1}  # the base is unchanged
    # the default agent is never inherited, and an extending recipe names its own agent
    (tmp_path / "base" / "default.toml").write_text('name = "d"\n[card]\ndefault = true\nsummary = "d"\n')
    (tmp_path / "mine.toml").write_text('extends = "base/default.toml"\nname = "mine"\n')
    assert read_recipe(tmp_path / "mine.toml")["card"] == {"summary": "d"}
    (tmp_path / "own.toml").write_text('extends = "base/default.toml"\nname = "own"\n[card]\ndefault = true\n')
    assert read_recipe(tmp_path / "own.toml")["card"]["default"] is True
    (tmp_path / "noname.toml").write_text('extends = "base/default.toml"\n')
    with pytest.raises(CommandError, match=r"noname.toml: extends 'base/default.toml' but sets no name of its own"):
        read_recipe(tmp_path / "noname.toml")
    (tmp_path / "base" / "a.toml").write_text('extends = "../c.toml"\n')
    with pytest.raises(CommandError, match="comes back to a recipe it passed through") as e:
        read_recipe(tmp_path / "c.toml")
    assert "\n" not in str(e.value)
    (tmp_path / "d.toml").write_text('extends = "nothere.toml"\n')
    with pytest.raises(CommandError, match=r"d.toml: extends = 'nothere.toml': no such recipe file"):
        read_recipe(tmp_path / "d.toml")
    (tmp_path / "e.toml").write_text("extends = 3\n")
    with pytest.raises(CommandError, match="extends must name a recipe file"):
        read_recipe(tmp_path / "e.toml")
    (tmp_path / "f.toml").write_text('extends = "f.toml"\n')
    with pytest.raises(CommandError, match="comes back"):
        read_recipe(tmp_path / "f.toml")


def test_shipped_recipes_that_extend_resolve_to_their_settings(tmp_path):
    """The recipes written as another's plus their differences resolve to a whole recipe: no ``extends`` key left,
    every section of the base, their own values on top."""
    seven = read_recipe(CONFIGS / "agents" / "tsrm-demae-learned7.toml")
    paper = read_recipe(CONFIGS / "agents" / "tsrm-demae-paper-protocol.toml")
    assert "extends" not in paper and set(paper) == set(seven)
    assert paper["train"]["protocol"] == "paper" and seven["train"]["protocol"] == "lineage"
    assert paper["reward"]["k_regret"] == 0.15 and "k_regret" not in seven["reward"]
    assert paper["agent"] == seven["agent"]
    six = read_recipe(CONFIGS / "agents" / "tsrm-demae-learned6.toml")
    assert six["detections"] == {"shipped": "learned6", "name": "learned6"} and six["card"]["default"] is False


def test_every_shipped_recipe_names_no_machine_path():
    for path in CONFIGS.rglob("*.toml"):
        for line in path.read_text().splitlines():
            if not line.startswith("#"):
                assert "/work/" not in line and "/home/" not in line and "/tmp/" not in line, (path, line)


# -- a run's settings end to end ----------------------------------------------------------------------------------


def test_train_recipe_and_resume_refusal(pixel_world, tmp_path, capsys):
    """K_d = 0.3 from a recipe file and --set reaches the run; a resume keeps it; another value is refused in one
    line naming it; the run's recipe.toml trains the same run again."""
    recipe = tmp_path / "kd.toml"
    recipe.write_text(
        '[train]\nalgo = "batched"\npreset = "cpu"\nnum_envs = 4\nrollout_steps = 5\n'
        "checkpoint_every = 2\nlog_every = 1\nlr = 1e-3\n[reward]\nk_distance = 0.3\n"
        "[agent]\ndropout = 0.2\n"
    )
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--config",
                str(recipe),
                "--set",
                "train.updates=2",
                "--data",
                str(pixel_world),
                "--features",
                FEATS,
                "--detections",
                "oracle",
                "--out",
                str(run),
                "--quiet",
            ]
        )
        == 0
    )
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["reward"]["k_distance"] == 0.3 and cfg["train"]["reward_settings"] == {"k_distance": 0.3}
    assert cfg["agent"]["dropout"] == 0.2 and cfg["train"]["updates"] == 2
    saved = read_recipe(run / "recipe.toml")
    assert saved["reward"]["k_distance"] == 0.3 and saved["agent"]["dropout"] == 0.2
    assert main(["train", "--out", str(run), "--updates", "4", "--quiet"]) == 0  # resumed with its own K_d
    assert json.loads((run / "config.json").read_text())["reward"]["k_distance"] == 0.3
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--k-distance", "0.15", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "another configuration (reward.k_distance): 0.3 saved, 0.15 given" in err
    assert main(["train", "--out", str(run), "--set", "agent.dropout=0.45", "--quiet"]) == 2
    assert "(agent.dropout)" in capsys.readouterr().err
    again = tmp_path / "again"
    assert main(["train", "--config", str(run / "recipe.toml"), "--out", str(again), "--quiet"]) == 0
    a, b = (json.loads((p / "config.json").read_text()) for p in (run, again))
    assert {k: v for k, v in a["train"].items() if k not in BUDGET_FIELDS} == {
        k: v for k, v in b["train"].items() if k not in BUDGET_FIELDS
    }
    assert a["reward"] == b["reward"] and a["agent"] == b["agent"]


def test_build_refuses_unknown_and_names_the_section():
    with pytest.raises(CommandError, match=r"\[agent\]: no setting hiden"):
        build(AgentConfig, {"hiden": 3}, "agent")


def test_pretrain_options_come_from_pretrain_config():
    """`tsnav pretrain`: one option per PretrainConfig field (its old names --patch and --workers kept), a recipe's
    [pretrain] section and --set under the options given."""
    from tsnav.pretrain.command import config_from_args
    from tsnav.pretrain.train import PretrainConfig

    assert config_from_args(parse("pretrain", ["--data", "d", "--out", "o"])) == PretrainConfig()
    c = config_from_args(
        parse(
            "pretrain",
            [
                "--data",
                "d",
                "--out",
                "o",
                "--patch",
                "8",
                "--num-workers",
                "2",
                "--no-preload",
                "--set",
                "pretrain.betas=[0.9, 0.99]",
                "--set",
                "pretrain.steps=7",
                "--steps",
                "5",
            ],
        )
    )
    assert (c.patch_size, c.num_workers, c.preload, c.betas, c.steps) == (8, 2, False, (0.9, 0.99), 5)
    with pytest.raises(CommandError, match="unknown method 'dino'"):
        config_from_args(parse("pretrain", ["--data", "d", "--out", "o", "--method", "dino"]))


def test_every_parser_refuses_abbreviations():
    """Every ArgumentParser of the package and of bench/ is made with allow_abbrev=False (tsnav's subcommands by
    cli.py, through tsnav.settings.Parser and refuse_abbreviations)."""
    import re

    for path in [*(ROOT / "src").rglob("*.py"), *(ROOT / "bench").glob("*.py")]:
        text = path.read_text()
        for m in re.finditer(r"ArgumentParser\(", text):  # the call's arguments up to its closing parenthesis
            depth, i = 1, m.end()
            while depth and i < len(text):
                depth += {"(": 1, ")": -1}.get(text[i], 0)
                i += 1
            assert "allow_abbrev=False" in text[m.end() : i] or path.name == "settings.py", (path, text[m.start() : i])


def test_release_make_refuses_before_any_work(tmp_path, capsys):
    """`tsnav release make`: replacing a shipped agent needs its name, and the recipe's own mistakes are refused
    before a folder is made; nothing is written into the package."""
    recipe = CONFIGS / "agents" / "tsrm-demae-learned7.toml"
    work = tmp_path / "work"
    before = sorted(p.name for p in WEIGHTS.iterdir())
    assert main(["release", "make", str(recipe), "--work", str(work), "--replace-shipped", "tsrm-demae-learned6"]) == 2
    assert "the recipe makes 'tsrm-demae-learned7'" in capsys.readouterr().err and not work.exists()
    assert main(["release", "make", str(recipe), "--work", str(work), "--set", 'train.data="/x"']) == 2
    assert "[train]: data is the work folder's" in capsys.readouterr().err and not work.exists()
    assert main(["release", "make", str(recipe), "--work", str(work), "--set", 'train.algo="a3c"']) == 2
    assert "algo batched" in capsys.readouterr().err
    assert main(["release", "make", str(recipe), "--work", str(work), "--set", "convergence.chunk=0"]) == 2
    assert "--chunk must be >= 1" in capsys.readouterr().err
    assert sorted(p.name for p in WEIGHTS.iterdir()) == before


def test_agent_card_is_written_from_the_recipe(tmp_path):
    from tsnav.detect.shipped import shipped_meta
    from tsnav.pipeline.agent_recipe import resolve_agent
    from tsnav.pipeline.release import CARD_REQUIRED, agent_card

    r = resolve_agent(read_recipe(CONFIGS / "agents" / "tsrm-demae-learned7.toml"), tmp_path)
    card = agent_card(r, tmp_path)
    assert all(k in card for k in CARD_REQUIRED)
    shipped = json.loads((WEIGHTS / r.name / "card.json").read_text())
    for k in (
        "name",
        "world_preset",
        "world_version",
        "image_size",
        "detector_shipped",
        "detector_fingerprint",
        "detections",
        "summary",
        "protocol",
        "encoder_id",
    ):
        assert card[k] == shipped[k], k
    assert card["detector_fingerprint"] == shipped_meta("learned7")["fingerprint"]


def test_train_reads_its_sections_of_an_agent_recipe(capsys, tmp_path):
    """``tsnav train --config configs/agents/NAME.toml`` runs the recipe's [train], [reward] and [agent] (the
    other sections are tsnav release make's, named in one line); a misspelt section is still refused."""
    from tsnav.pipeline.agent_recipe import SECTIONS as AGENT_SECTIONS
    from tsnav.rl.recipe import AGENT_RECIPE_KEYS, SECTIONS, recipe_from_args, resolve_run

    assert set(AGENT_SECTIONS) - set(SECTIONS) == set(AGENT_RECIPE_KEYS) - {"name"}
    path = CONFIGS / "agents" / "tsrm-demae-learned7.toml"
    recipe = recipe_from_args(parse("train", ["--config", str(path), "--data", "d", "--out", "o"]))
    assert "world" in capsys.readouterr().err
    cfg, agent = resolve_run(recipe)
    full = read_recipe(path)
    assert (cfg.lr, cfg.seed, cfg.num_envs, cfg.protocol) == (
        full["train"]["lr"],
        full["train"]["seed"],
        full["train"]["num_envs"],
        full["train"]["protocol"],
    )
    assert agent.dropout == full["agent"]["dropout"]
    (tmp_path / "r.toml").write_text(path.read_text().replace("[world]", "[wrold]"))
    with pytest.raises(CommandError, match="wrold"):
        recipe_from_args(parse("train", ["--config", str(tmp_path / "r.toml"), "--data", "d", "--out", "o"]))


# -- the RoboTHOR agent's recipe -----------------------------------------------------------------------------------

ROBOTHOR = CONFIGS / "agents" / "tsrm-demae-robothor.toml"


def test_robothor_recipe_is_learned7s_run_on_robothor(tmp_path):
    """configs/agents/tsrm-demae-robothor.toml: learned7's [train], [reward] and [agent] but max_steps and the
    detection tables, on the robothor-real world with the robothor2 detector, its checkpoints scored on the
    challenge's train episodes after training (never on the val scenes, the benchmark)."""
    from tsnav.pipeline.agent_recipe import resolve_agent

    r = resolve_agent(read_recipe(ROBOTHOR), tmp_path)
    seven = resolve_agent(read_recipe(CONFIGS / "agents" / "tsrm-demae-learned7.toml"), tmp_path)
    ours, theirs = identity_recipe(*r.run), identity_recipe(*seven.run)
    # what the RoboTHOR run changed: longer episodes, its tables, seed 1, two staggered processes, checkpoints every
    # 100 updates (and its budget: below)
    changed = {
        "max_steps": 100,
        "detections": "robothor2",
        "seed": 1,
        "procs": 2,
        "ranks": "staggered",
        "checkpoint_every": 100,
    }
    assert {k: ours["train"][k] for k in changed} == changed
    for d in (ours, theirs):
        for k in changed:
            d["train"].pop(k)
    assert first_difference(theirs, ours) is None
    assert (r.world.preset, r.world.version) == ("robothor-real", 2)
    assert (r.detections.shipped, r.detections.name, r.detections.evaluated) == ("robothor2", "robothor2", "robothor3")
    # its pretraining streamed the frames (preload off); otherwise learned7's
    assert r.pretrain.preload is False and replace(r.pretrain, preload=True) == seven.pretrain
    assert r.features == seven.features
    assert (r.run[0].split, r.run[0].algo, r.run[0].reward, r.run[0].protocol) == (
        "train",
        "batched",
        "tsrm",
        "lineage",
    )
    assert (r.run[0].milestone_every, r.run[0].updates, r.run[0].episodes) == (250, None, 1_500_000)
    assert (r.scoring.episodes, r.scoring.chunks, r.scoring.challenge) == ("challenge-train", False, "")
    assert r.select.per_room_type and not r.card.get("default")
    assert "RoboTHOR" in r.card["summary"] and "RoboTHOR" in r.card["rooms"]
    # the resolved recipe reads back to the same agent
    again = resolve_agent(read_recipe_text(dump_recipe(r.to_recipe())), tmp_path)
    assert again.to_recipe() == r.to_recipe() and again.scoring == r.scoring


def test_recipe_names_shipped_detectors_only(tmp_path):
    """[detections] shipped and evaluated must name detectors tsnav ships: refused in one line before any work."""
    from tsnav.pipeline.agent_recipe import resolve_agent

    recipe = read_recipe(ROBOTHOR)
    for key in ("shipped", "evaluated"):
        bad = {**recipe, "detections": {**recipe["detections"], key: "robothor9"}}
        with pytest.raises(CommandError, match=rf"\[detections\]: {key} 'robothor9' is no shipped detector"):
            resolve_agent(bad, tmp_path)


def test_robothor_recipe_never_scores_on_its_benchmark(tmp_path, capsys):
    """The val scenes are RoboTHOR's benchmark: a recipe scoring checkpoints on them is refused, as are challenge
    episodes for an iTHOR agent and a challenge-train scoring without the challenge's folder; all before any work."""
    from tsnav.pipeline.agent_recipe import resolve_agent

    recipe = read_recipe(ROBOTHOR)
    with pytest.raises(CommandError, match=r'episodes "val" would choose checkpoints on the robothor-real val scenes'):
        resolve_agent(apply_sets(recipe, ['scoring.episodes="val"'], ("scoring",)), tmp_path)
    seven = read_recipe(CONFIGS / "agents" / "tsrm-demae-learned7.toml")
    with pytest.raises(CommandError, match="RoboTHOR's, not of the ithor-real world"):
        resolve_agent(apply_sets(seven, ['scoring.episodes="challenge-train"'], ("scoring",)), tmp_path)
    with pytest.raises(CommandError, match="episodes must be one of val, challenge-train, none"):
        resolve_agent(apply_sets(recipe, ['scoring.episodes="test"'], ("scoring",)), tmp_path)
    with pytest.raises(CommandError, match=r"chunks = false needs \[select\] per_room_type"):
        resolve_agent(apply_sets(recipe, ['select.per_room_type="none"'], ("select",)), tmp_path)
    none = resolve_agent(
        apply_sets(recipe, ['scoring.episodes="none"', 'select.per_room_type="none"'], ("scoring", "select")), tmp_path
    )
    assert none.scoring.episodes == "none"  # nothing scored: the last checkpoint is packed
    work = tmp_path / "work"
    assert main(["release", "make", str(ROBOTHOR), "--work", str(work)]) == 2
    err = capsys.readouterr().err
    assert "give their folder with --challenge DIR" in err and len(err.strip().splitlines()) == 1
    assert main(["release", "make", str(ROBOTHOR), "--work", str(work), "--challenge", str(tmp_path)]) == 2
    assert "no train/*.json.gz" in capsys.readouterr().err
    assert not work.exists()


def test_recipe_builds_train_apartments_the_val_way(tmp_path, monkeypatch):
    """[world] infer_train_objects builds the robothor-real train apartments the way the val ones are, from the
    challenge's folder that scores the checkpoints; refused for another world, without that folder, and (in one line,
    before any scene is built) when a train scene has no episodes there."""
    import gzip

    import tsnav.world.build as world_build
    from tsnav.pipeline.agent_recipe import make_agent, resolve_agent
    from tsnav.world.presets import preset_scenes

    recipe = apply_sets(read_recipe(ROBOTHOR), ["world.infer_train_objects=true"], ("world",))
    seven = read_recipe(CONFIGS / "agents" / "tsrm-demae-learned7.toml")
    with pytest.raises(CommandError, match="infer_train_objects applies to the robothor-real world, not 'ithor-real'"):
        resolve_agent(apply_sets(seven, ["world.infer_train_objects=true"], ("world",)), tmp_path)
    with pytest.raises(CommandError, match='goes with \\[scoring\\] episodes = "challenge-train"'):
        resolve_agent(
            apply_sets(recipe, ['scoring.episodes="none"', 'select.per_room_type="none"'], ("scoring", "select")),
            tmp_path,
        )
    r = resolve_agent(recipe, tmp_path)
    assert r.world.infer_train_objects and not resolve_agent(read_recipe(ROBOTHOR), tmp_path).world.infer_train_objects
    built = []
    monkeypatch.setattr(world_build, "build_dataset", lambda out, preset, names, cfg, workers: built.append(cfg))
    challenge = tmp_path / "challenge"
    (challenge / "train").mkdir(parents=True)
    train = [n for n in preset_scenes("robothor-real") if "_Train" in n]
    for n in train[:-1]:
        (challenge / "train" / f"{n}.json.gz").write_bytes(gzip.compress(b"[]"))
    with pytest.raises(CommandError, match=rf"infer_train_objects: no challenge train episodes of {train[-1]}"):
        make_agent(r, tmp_path / "work", until="world", challenge=challenge)
    assert not built
    (challenge / "train" / f"{train[-1]}.json.gz").write_bytes(gzip.compress(b"[]"))
    make_agent(r, tmp_path / "work", until="world", challenge=challenge)
    assert built[0].infer_train == str(challenge.resolve()) and built[0].world == "robothor-real"
    built.clear()
    make_agent(resolve_agent(read_recipe(ROBOTHOR), tmp_path), tmp_path / "work2", until="world", challenge=challenge)
    assert built[0].infer_train is None  # the recipe's default: train apartments from their records
    built.clear()
    make_agent(
        resolve_agent(apply_sets(recipe, ["world.seed=1"], ("world",)), tmp_path),
        tmp_path / "w3",
        challenge=challenge,
        until="world",
    )
    assert built[0].seed == 1 and built[0].infer_train == str(challenge.resolve())  # redrawn train surfaces
    for bad, where in (("world.seed=2", seven), ("world.seed=-1", recipe)):
        with pytest.raises(CommandError, match=r"\[world\]: seed"):
            resolve_agent(apply_sets(where, [bad], ("world",)), tmp_path)


def test_recipe_builds_the_rooms_again_for_a_detector_of_finer_frames(tmp_path, monkeypatch):
    """A recipe whose shipped detector reads finer frames than its world's (tsnav detect --frames) builds the rooms a
    second time at the detector's side in WORK/world-<side>px, with the same rules (seed, inferred objects); a
    detector of the world's side builds nothing more."""
    import gzip

    import tsnav.pipeline.agent_recipe as agent_recipe
    import tsnav.world.build as world_build
    from tsnav.pipeline.agent_recipe import make_agent, resolve_agent
    from tsnav.world.presets import preset_scenes

    challenge = tmp_path / "challenge"
    (challenge / "train").mkdir(parents=True)
    for n in preset_scenes("robothor-real"):
        if "_Train" in n:
            (challenge / "train" / f"{n}.json.gz").write_bytes(gzip.compress(b"[]"))
    recipe = apply_sets(read_recipe(ROBOTHOR), ["world.infer_train_objects=true", "world.seed=1"], ("world",))
    built = []
    monkeypatch.setattr(world_build, "build_dataset", lambda out, preset, names, cfg, workers: built.append((out, cfg)))
    r = resolve_agent(recipe, tmp_path)
    monkeypatch.setattr(agent_recipe, "shipped_side", lambda name=None: 256)
    make_agent(r, tmp_path / "work", until="world", challenge=challenge)
    (world, cfg), (fine, fine_cfg) = built
    assert world == tmp_path / "work" / "world" and fine == tmp_path / "work" / "world-256px"
    assert (cfg.image_size, fine_cfg.image_size) == (128, 256)
    assert fine_cfg.seed == cfg.seed == 1 and fine_cfg.infer_train == cfg.infer_train == str(challenge.resolve())
    built.clear()
    monkeypatch.setattr(agent_recipe, "shipped_side", lambda name=None: 128)
    make_agent(r, tmp_path / "work2", until="world", challenge=challenge)
    assert [out for out, _ in built] == [tmp_path / "work2" / "world"]


def test_robothor_agent_card(tmp_path, monkeypatch):
    """agent_card of the RoboTHOR recipe: its eval split and episodes, the val scenes and no test rooms (the
    lead registers the robothor2 detector; here a stand-in's fingerprint)."""
    from tsnav.data.names import robothor_scenes
    from tsnav.detect import shipped
    from tsnav.pipeline.agent_recipe import resolve_agent
    from tsnav.pipeline.release import CARD_REQUIRED, agent_card

    monkeypatch.setattr(shipped, "shipped_meta", lambda name=None: {"fingerprint": f"learned-{name}"})
    world = tmp_path / "world"
    for n in robothor_scenes():  # scene folders that list_scenes reads: the 75 apartments and their splits
        (world / n).mkdir(parents=True)
        (world / n / "scene.json").write_text(json.dumps({"split": "train" if "Train" in n else "val"}))
        (world / n / "COMPLETE").write_text("")
    r = resolve_agent(read_recipe(ROBOTHOR), tmp_path)
    card = agent_card(r, world)
    assert all(k in card for k in CARD_REQUIRED)
    assert (card["world_preset"], card["world_version"], card["image_size"]) == ("robothor-real", 2, 128)
    # trained on robothor2's tables, evaluated with robothor3 swapped in ([detections] evaluated): the card's
    # detector is the one its figures are of, and it names the one of training
    assert (card["detector_shipped"], card["detections"], card["detector_fingerprint"]) == (
        "robothor3",
        "robothor3",
        "learned-robothor3",
    )
    assert (card["trained_detector_shipped"], card["trained_detections"]) == ("robothor2", "robothor2")
    assert (card["eval_split"], card["episodes"]) == ("val", "challenge")
    assert card["val_rooms"] == robothor_scenes("val") and "test_rooms" not in card
    assert "--challenge CHALLENGE_DIR" in card["commands"][0]
    # an iTHOR card is written as before: no eval_split or episodes
    seven = agent_card(resolve_agent(read_recipe(CONFIGS / "agents" / "tsrm-demae-learned7.toml"), tmp_path), world)
    assert not {"eval_split", "episodes"} & set(seven) and {"val_rooms", "test_rooms"} <= set(seven)
    assert not {"trained_detector_shipped", "trained_detections"} & set(seven)
