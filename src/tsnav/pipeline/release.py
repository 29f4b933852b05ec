"""``tsnav release``: the trained agent that ships with tsnav, and the one command that evaluates it.

A shipped agent is a folder of ``tsnav/agent/weights/<name>/`` (package data, nothing downloaded):

* ``config.json``: the training run's resolved configuration (``format: tsnav-train-run``), its feature cache
  renamed to the shipped encoder's, so that the folder loads as a run (:func:`tsnav.rl.checkpoint.load_policy`);
* ``best/model.safetensors`` and ``best/state.json``: the policy (LSTM actor-critic, paper III-D) chosen on
  validation episodes; no optimizer state;
* ``encoder.safetensors``: the DE-MAE ViT encoder (paper III-C) in float16 (:data:`ENCODER_DTYPE`; it is read
  back into float32; ``tests/pipeline/test_release.py`` holds its features to those of the float32 encoder);
* ``card.json`` and ``card.md``: the model card (world and its version, rooms, protocol, detector, budget in
  updates / episodes / env steps, validation and test figures under both success protocols, the command that
  trained it), and the version of tsnav that packed it (``tsnav_version``; cards packed before 0.2.0 have none).

The detector is not copied: the card names a detector shipped with tsnav (:mod:`tsnav.detect.shipped`), whose
fingerprint must match the one recorded at packing.

``tsnav release eval`` builds the 20 real test rooms (``ithor-real`` at the card's frame size), writes the
shipped detector's tables and the shipped encoder's features into them, draws the test episodes exactly as the
experiments do (250 per room type, seed 0) and evaluates the agent greedily, beside the scripted explorer with
the same stage switch and the random policy; every step is skipped when its output exists. A card that names an
``eval_split`` and ``episodes = "challenge"`` (a RoboTHOR agent, :data:`~tsnav.pipeline.agent_steps.WORLD_EVAL`) is
evaluated on that split by default (RoboTHOR has no test split): its rooms only (the 15 val scenes, built into
``out/release/world-robothor-real-vN`` by default), the challenge's episodes of the split packaged with tsnav,
converted under each protocol by :mod:`tsnav.sim.challenge` and written once beside the results. When nothing changed
since the last evaluation into the same folder (:func:`release_inputs`: the agent's and encoder's weights, the
rooms, detection tables and feature caches, the episode lists and the settings, recorded in ``results.json``),
a second run prints the saved table and says so in one line; ``--force`` evaluates again. A ``--data`` folder that
does not exist is refused unless ``--build-world`` asks for the rooms to be built there (without ``--data`` the
default folder is built). An agent whose detector reads finer frames than its rooms (``tsnav detect --frames``; the
shipped detector's own frame side) gets the rooms built again at that side beside ``--data`` (``DATA-256px``),
the detector's tables written there and scaled into ``--data``'s rooms. ``tsnav release pack`` makes such a folder from a training run and a pretraining run; ``tsnav release make
RECIPE --work DIR`` makes a whole agent from its recipe (``configs/agents/NAME.toml``,
:mod:`tsnav.pipeline.agent_recipe`) into ``DIR/agent/NAME``, and writes into the package only when asked by name
(``--replace-shipped NAME``). A packed ``config.json`` holds no machine path.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import hashlib
import json
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING

from .. import __version__
from ..atomic import atomic_write_text
from ..errors import CommandError, read_json
from ..metrics import METRICS
from ..protocol import PROTOCOLS, check_protocol, protocol_line
from ..settings import add_shared, apply_sets, dump_recipe, read_recipe
from .agent_steps import STEPS, WORLD_EVAL

if TYPE_CHECKING:  # the recipe's steps import torch: read on use, so that `release list` and a saved table need none
    from .agent_recipe import AgentRecipe

#: Where shipped agents live (package data of ``tsnav.agent``).
WEIGHTS = Path(__file__).resolve().parent.parent / "agent" / "weights"
#: dtype the encoder is stored in (a torch dtype's name); weights are read back into float32. torch is imported
#: only where tensors are read or written, so that ``tsnav release list`` and a release evaluation whose saved
#: table is printed (nothing changed) start without it.
ENCODER_DTYPE = "float16"
CARD_FORMAT = "tsnav-agent-card"
#: Fields a card must give when packing.
CARD_REQUIRED = (
    "name",
    "summary",
    "world_preset",
    "world_version",
    "image_size",
    "detector_shipped",
    "detector_fingerprint",
    "detections",
    "protocol",
    "budget",
)
#: Episodes of the release evaluation per split: (per room type, seed). Test: the experiments' list (``tsnav
#: experiment``, 250 per room type, seed 0); val: the convergence runs' list (100 per room type, seed 0).
SPLIT_EPISODES = {"test": (250, 0), "val": (100, 0)}


def eval_split(card: dict) -> str:
    """The split ``tsnav release eval`` evaluates the card's agent on unless told: the card's ``eval_split``, else
    ``test``."""
    return card.get("eval_split") or "test"


def challenge_card(card: dict) -> bool:
    """Whether the card's agent is evaluated on the RoboTHOR challenge's episodes (``episodes = "challenge"``)."""
    return card.get("episodes") == "challenge"


def split_rooms(card: dict, split: str) -> list[str]:
    """The rooms of ``split`` that the card's agent is evaluated on: the card's ``<split>_rooms``, else its world's
    rooms of the split; a one-line error when the world has none (RoboTHOR has no test split)."""
    from ..data.names import ithor_scenes, robothor_scenes

    if card.get(f"{split}_rooms"):
        return list(card[f"{split}_rooms"])
    world = card.get("world_preset", "ithor-real")
    names = robothor_scenes(split) if world.startswith("robothor") else ithor_scenes(split=split)
    if not names:
        raise CommandError(
            f"the {world} world has no {split} rooms: evaluate this agent with --split {eval_split(card)}"
        )
    return names


def rooms_text(card: dict, n: int, split: str) -> str:
    """What the table's header calls the rooms and episodes: ``20 real test rooms``, or ``15 RoboTHOR val scenes,
    challenge episodes``."""
    return f"{n} RoboTHOR {split} scenes, challenge episodes" if challenge_card(card) else f"{n} real {split} rooms"


def shipped_agents() -> dict[str, Path]:
    """Name -> folder of every agent shipped in the package."""
    if not WEIGHTS.is_dir():
        return {}
    return {p.name: p for p in sorted(WEIGHTS.iterdir()) if (p / "card.json").exists()}


def default_agent() -> str | None:
    """The agent ``tsnav release eval`` uses unless told otherwise: the one the card marks ``default``, else the
    newest by name."""
    agents = shipped_agents()
    for name, p in agents.items():
        if read_card(p).get("default"):
            return name
    return next(reversed(agents), None) if agents else None


def agent_folder(name: str | None) -> Path:
    """The folder of shipped agent ``name`` (default :func:`default_agent`), or a folder path given directly."""
    if name and Path(name).is_dir():
        folder = Path(name)
    else:
        agents = shipped_agents()
        name = name or default_agent()
        if name is None:
            raise CommandError("no agent ships with this tsnav (tsnav release pack makes one)")
        if name not in agents:
            raise CommandError(f"no shipped agent named {name!r} (choose from {', '.join(agents) or 'none'})")
        folder = agents[name]
    for f in ("card.json", "config.json", "encoder.safetensors", "best/model.safetensors", "best/state.json"):
        if not (folder / f).exists():
            raise CommandError(f"{folder}: not a complete shipped agent (no {f})")
    return folder


def read_card(folder: str | Path) -> dict:
    p = Path(folder) / "card.json"
    card = read_json(p, missing="missing")
    if card.get("format") != CARD_FORMAT:
        raise CommandError(f"{p}: not a tsnav agent card")
    return card


# -- packing ---------------------------------------------------------------------------------------------------


def pack_encoder(src: str | Path, dst: str | Path) -> None:
    """Copy a ``tsnav`` encoder file with its floating-point tensors stored as :data:`ENCODER_DTYPE`; a file stored
    so already (a shipped agent's encoder) is copied byte for byte, so that agents sharing an encoder ship one file."""
    import torch

    from ..checkpoint import load_tensors, save_tensors

    sd, meta = load_tensors(src)
    if meta.get("format") != "tsnav-encoder":
        raise CommandError(f"{src}: not a tsnav encoder file")
    if meta.get("stored_dtype") == ENCODER_DTYPE:
        shutil.copyfile(src, dst)
        return
    dtype = getattr(torch, ENCODER_DTYPE)
    small = {k: (v.to(dtype) if v.is_floating_point() else v).contiguous() for k, v in sd.items()}
    save_tensors(dst, small, {**meta, "stored_dtype": ENCODER_DTYPE})


def pack(run: str | Path, checkpoint: str | Path, encoder_run: str | Path, out: str | Path, card: dict) -> Path:
    """Write a shipped-agent folder ``out`` from training run ``run`` (its ``checkpoint`` folder), the pretraining
    run ``encoder_run`` (``encoder.safetensors``) and the model-card fields ``card`` (written as given, plus the
    files' provenance). The folder is assembled under a temporary name and renamed when whole; an existing
    ``out`` is refused."""
    from ..pretrain.features import load_encoder

    out = Path(out)
    if out.exists():
        raise CommandError(f"{out}: exists; remove it or choose another name")
    run, checkpoint, encoder_run = Path(run), Path(checkpoint), Path(encoder_run)
    cfg = json.loads((run / "config.json").read_text())
    if cfg.get("format") != "tsnav-train-run":
        raise CommandError(f"{run}: not a training run (config.json)")
    if cfg.get("agent", {}).get("target_depth"):
        raise CommandError(
            f"{run}: reads a target depth ({cfg['agent']['target_depth']}); such agents are a measured lever, not "
            "packed (a readout would have to ship beside the encoder; the ground truth never ships)"
        )
    if cfg.get("agent", {}).get("mirror_policy"):
        raise CommandError(
            f"{run}: a mirror-symmetric agent (mirror_policy) is a measured lever, not packed: `tsnav release eval` "
            "does not build the caches of the flipped frames it reads"
        )
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "best").mkdir(parents=True)
    pack_encoder(encoder_run / "encoder.safetensors", tmp / "encoder.safetensors")
    enc = load_encoder(str(tmp / "encoder.safetensors"))
    features = f"{card.get('encoder_id', 'demae')}-{enc.fingerprint[:10]}"
    cfg["train"]["features"] = features
    cfg["train"]["data"] = ""  # no machine path ships: the rooms are the evaluation's (tsnav release eval --data)
    if isinstance(cfg.get("features"), dict) and "encoder" in cfg["features"]:
        cfg["features"]["encoder"] = (
            f"{Path(str(cfg['features']['encoder'])).name} (the pretraining run; packed "
            "in float16 as encoder.safetensors)"
        )
    cfg["shipped"] = {"trained_features": json.loads((run / "config.json").read_text())["train"]["features"]}
    (tmp / "config.json").write_text(json.dumps(cfg, indent=1) + "\n")
    shutil.copy2(checkpoint / "model.safetensors", tmp / "best" / "model.safetensors")
    state = json.loads((checkpoint / "state.json").read_text())
    state.pop("optimizer", None)
    (tmp / "best" / "state.json").write_text(json.dumps(state, indent=1) + "\n")
    full = {
        "format": CARD_FORMAT,
        **card,
        "tsnav_version": __version__,
        "features": features,
        "encoder_fingerprint": enc.fingerprint,
        "encoder": {
            "arch": enc.arch,
            "method": enc.method,
            "img_size": enc.img_size,
            "config": enc.config,
            "stored_dtype": "float16",
        },
        "policy_update": int(state.get("progress", state).get("update", -1)),
    }
    (tmp / "card.json").write_text(json.dumps(full, indent=1) + "\n")
    (tmp / "card.md").write_text(card_markdown(full))
    tmp.rename(out)
    return out


def card_markdown(card: dict) -> str:
    """The model card as Markdown (what a reader of the weights folder sees first)."""
    lines = [f"# tsnav agent `{card.get('name', '?')}`", "", card.get("summary", ""), ""]
    rows = [
        ("world", card.get("world")),
        ("rooms", card.get("rooms")),
        ("frames", card.get("frames")),
        ("detector", card.get("detector")),
        (
            "trained with",
            f"the shipped detector {card['trained_detector_shipped']}'s tables (evaluated with "
            f"{card.get('detector_shipped', '?')}'s)"
            if card.get("trained_detector_shipped")
            else None,
        ),
        ("encoder", card.get("encoder_text")),
        ("policy", card.get("policy_text")),
        ("reward", card.get("reward")),
        ("training protocol", card.get("protocol")),
        ("budget", card.get("budget")),
        ("checkpoint", card.get("checkpoint_text")),
        ("machine", card.get("machine")),
        ("packed with", f"tsnav {card['tsnav_version']}" if card.get("tsnav_version") else None),
    ]
    lines += ["| | |", "|---|---|"] + [f"| {k} | {v} |" for k, v in rows if v]
    for title, key in (("Validation", "val"), ("Test", "test")):
        figs = card.get("figures", {}).get(key)
        if not figs:
            continue
        if challenge_card(card) and key == eval_split(card):
            title = f"RoboTHOR {key} scenes, the challenge's episodes"
        lines += [
            "",
            f"## {title} ({figs.get('episodes', '?')} episodes, greedy)",
            "",
            "| protocol | policy | subset | " + " | ".join(METRICS) + " |",
            "|---|---|---|" + "---:|" * len(METRICS),
        ]
        for row in figs.get("rows", []):
            for sub in ("ALL", "L>=5"):
                m = row["metrics"].get(sub)
                if m:
                    lines.append(
                        f"| {row['protocol']} | {row['policy']} | {sub} | "
                        + " | ".join(f"{100 * m[k]:.2f}" for k in METRICS)
                        + " |"
                    )
    if card.get("commands"):
        lines += ["", "## How it was made", ""] + [f"    {c}" for c in card["commands"]]
    if challenge_card(card):
        lines += [
            "",
            f"Evaluate it from a fresh clone: `tsnav release eval --agent {card.get('name', 'NAME')}` (builds the "
            f"{eval_split(card)} scenes, the detector's tables and the features it needs, converts the challenge's "
            f"{eval_split(card)} episodes packaged with tsnav, then prints this table).",
        ]
    else:
        lines += [
            "",
            "Evaluate it from a fresh clone: `tsnav release eval` (builds the test rooms, the detector's "
            "tables and the features it needs, then prints this table).",
        ]
    if card.get("notes"):
        lines += ["", "## Notes", ""] + [f"- {n}" for n in card["notes"]]
    return "\n".join(lines) + "\n"


# -- evaluation ------------------------------------------------------------------------------------------------


def say(msg: str) -> None:
    print(f"[release] {msg}", flush=True)


def detector_frames(card: dict) -> int | None:
    """The frame side of the card's shipped detector when it is not the world's (a detector that reads finer frames
    than the agent, ``tsnav detect --frames``), else None."""
    from ..detect.shipped import shipped_side

    side = shipped_side(card["detector_shipped"])
    return side if side != int(card.get("image_size", 128)) else None


def frames_folder(data: Path, side: int) -> Path:
    """Where ``tsnav release eval`` builds the rooms again at ``side`` px for a detector of :func:`detector_frames`:
    beside ``data``, named after it."""
    return data.with_name(f"{data.name}-{side}px")


def ensure_test_world(
    data: Path, card: dict, workers: int, split: str = "test", image_size: int | None = None
) -> list[str]:
    """Build the world's rooms of ``split`` into ``data`` (finished rooms are skipped), with frames of the card's
    side or of ``image_size``; returns their names."""
    from ..world.build import BuildConfig, build_dataset

    world = card.get("world_preset", "ithor-real")
    names = split_rooms(card, split)
    side = int(image_size or card.get("image_size", 128))
    cfg = BuildConfig.from_preset(world, image_size=side, world_version=card.get("world_version"))
    t0 = time.perf_counter()
    try:
        stats = build_dataset(data, preset=world, scenes=names, cfg=cfg, workers=workers)
    except ValueError as e:
        if "version" not in str(e):
            raise
        raise CommandError(
            f"{data} holds rooms of another {world} rules version than this agent's (version "
            f"{card.get('world_version')}): pass --data and --out with new folders, or remove "
            f"{data}"
        ) from None
    built = sum(not s.skipped for s in stats)
    if built:
        what = "test rooms" if world == "ithor-real" else f"{split} scenes"
        at = f" at {side} px (the detector's frames)" if image_size else ""
        say(f"world: built {built} of {len(names)} {what}{at} in {time.perf_counter() - t0:.0f} s")
    return names


def ensure_release_features(
    data: Path,
    folder: Path,
    card: dict,
    batch_size: int = 128,
    split: str = "test",
    progress: bool = True,
    workers: int | None = None,
) -> str:
    """Cache the shipped encoder's features in the rooms of ``split``; the name must be the card's. ``workers``
    processes on one thread each (None: one per core)."""
    from ..pretrain.features import cache_features, load_encoder
    from ..scene_pool import default_workers

    enc = load_encoder(str(folder / "encoder.safetensors"))
    if enc.fingerprint != card["encoder_fingerprint"]:
        raise CommandError(
            f"{folder / 'encoder.safetensors'}: its weights do not match the card's fingerprint "
            f"({enc.fingerprint} vs {card['encoder_fingerprint']})"
        )
    cache_features(
        enc,
        data,
        card["features"],
        batch_size=batch_size,
        split=split,
        progress=progress,
        workers=workers or default_workers(),
    )  # one thread per process, as the agent's own features were cached
    return card["features"]


def ensure_release_detections(
    data: Path,
    card: dict,
    split: str | None = None,
    say=say,
    progress: bool = True,
    workers: int | None = None,
    frames: Path | None = None,
) -> str:
    """Write the card's shipped detector's tables into the rooms of ``data`` (of ``split`` only, when given),
    refusing tables of another detector; ``workers`` processes (None: one per core). A detector of
    :func:`detector_frames` reads the rooms built at its side in ``frames`` and its boxes are scaled to ``data``'s
    frames (:func:`~tsnav.pipeline.detector_steps.write_learned_tables` with ``frames``)."""
    from ..detect.shipped import shipped_meta

    det = card["detector_shipped"]
    if shipped_meta(det).get("fingerprint") != card["detector_fingerprint"]:
        raise CommandError(
            f"the shipped detector {det!r} is not the one of this agent's card ({card['detector_fingerprint']})"
        )
    from ..data.reader import load_scene
    from ..detect.shipped import shipped_detector
    from .detector_steps import learned_tables, write_learned_tables
    from ..scene_pool import default_workers

    have, kinds = learned_tables(data, card["detections"], split)
    if kinds and kinds[0] != card["detector_fingerprint"]:
        raise CommandError(
            f"{data}: its detections_{card['detections']}.hdf5 tables were made by another detector ({kinds[0]}) "
            f"than the card's {det} ({card['detector_fingerprint']}); remove them or evaluate in another --data folder"
        )
    if any(fp is None for fp in have.values()):
        side = detector_frames(card)
        if side and frames is None:
            raise CommandError(f"the shipped detector {det} reads {side}-px frames: give the rooms built at {side} px")
        write_learned_tables(
            data,
            card["detections"],
            shipped_detector(side or load_scene(next(iter(have))).image_size, det),
            say=say,
            progress=progress,
            source=f"the shipped detector {det}",
            workers=workers or default_workers(),
            split=split,
            frames=frames if side else None,
        )
    return card["detections"]


def protocol_kwargs(protocol: str) -> dict:
    """Keyword arguments of :func:`~tsnav.eval.runner.evaluate_to_folder` for a success protocol: named
    explicitly, so that an agent trained under the other one is evaluated across protocols."""
    return {"protocol": check_protocol(protocol)}


def release_episodes(data: Path, out: Path, protocol: str, split: str = "test", card: dict | None = None) -> Path:
    """The episode list of ``split`` under ``protocol``, made once: drawn as :data:`SPLIT_EPISODES` says, or, for a
    card whose ``episodes`` is ``challenge``, the RoboTHOR challenge's episodes of the split packaged with tsnav,
    converted on the card's rooms (:func:`~tsnav.pipeline.steps.ensure_challenge_episodes`)."""
    from .steps import ensure_challenge_episodes, ensure_episodes

    from ..sim.episodes import read_episodes

    per, seed = SPLIT_EPISODES[split]
    path = out / f"episodes_{split}_{protocol}.json"
    if path.exists():  # a list drawn on another world is never reused (its starts belong to other rooms)
        drawn_on = read_episodes(path)[1].get("data")
        if drawn_on and Path(drawn_on) != Path(data).resolve():
            raise CommandError(
                f"{path} was drawn on {drawn_on}, not on {Path(data).resolve()}: pass another --out (or remove {out})"
            )
    if card is not None and challenge_card(card):
        out.mkdir(parents=True, exist_ok=True)
        return ensure_challenge_episodes(data, split, path, protocol, scenes=split_rooms(card, split))
    return ensure_episodes(data, split, path, per, seed=seed, protocol=protocol)


#: Files of a room whose bytes the evaluation depends on (layout, state graph, success map), hashed into its identity.
ROOM_FILES = ("scene.json", "graph.json", "visible_object_map_1.5.json")
#: Episode-runner settings of the release evaluation (``EvalConfig`` defaults), part of what "nothing changed" means.
EVAL_SETTINGS = {"max_steps": 100, "greedy": True}


def _sha(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def release_inputs(
    folder: Path,
    card: dict,
    data: Path,
    out: Path,
    protocols: list[str],
    baselines: bool,
    split: str,
    batch_size: int = 4096,
) -> dict | None:
    """Everything a release evaluation's figures depend on, as a JSON-able record; None when something it reads is
    not there yet (the world's rooms of ``split``, their detection tables or feature caches, an episode list), i.e.
    when the evaluation has to run anyway. Two evaluations with equal records print the same table:

    * agent: the policy's and the encoder's weights (SHA-256 of ``best/model.safetensors`` and
      ``encoder.safetensors``), the training config's feature name and the card's detection tables (those the agent reads);
    * data: the world folder, per room of ``split`` a hash of its layout, state graph and success map
      (:data:`ROOM_FILES`), the fingerprint of its detection table (the detector's weights and temperature) and
      the feature cache's name (the encoder's fingerprint);
    * episodes: a hash of each protocol's episode list;
    * settings: split, protocols, baselines, batch size, C_target, :data:`EVAL_SETTINGS` and tsnav's version.

    Code changes between two releases of tsnav that keep the version are not seen: ``--force`` re-evaluates."""
    from .. import __version__
    from ..constants import C_TARGET
    from ..data.detections import read_fingerprint
    from ..data.reader import is_complete

    if not data.is_dir():
        return None
    names = split_rooms(card, split)  # the rooms ensure_test_world builds
    rooms = {}
    for n in names:
        room = data / n
        if not is_complete(room) or not (room / f"features_{card['features']}.hdf5").exists():
            return None
        fp = read_fingerprint(room, card["detections"])
        if fp is None:
            return None
        h = hashlib.sha256()
        for f in ROOM_FILES:
            if (room / f).exists():
                h.update(f.encode() + _sha(room / f).encode())
        rooms[n] = {"files": h.hexdigest()[:32], "detections": fp}
    episodes = {}
    for protocol in protocols:
        path = out / f"episodes_{split}_{protocol}.json"
        if not path.exists():
            return None
        episodes[protocol] = _sha(path)[:32]
    train = json.loads((folder / "config.json").read_text()).get("train", {})
    return {
        "agent": {
            "name": folder.name,
            "policy": _sha(folder / "best" / "model.safetensors"),
            "encoder": _sha(folder / "encoder.safetensors"),
            "features": train.get("features"),
            "detections": card["detections"],
        },
        "data": {"world": str(data.resolve()), "features": card["features"], "rooms": rooms},
        "episodes": episodes,
        "settings": {
            "split": split,
            "protocols": list(protocols),
            "baselines": bool(baselines),
            "batch_size": int(batch_size),
            "c_target": C_TARGET,
            **EVAL_SETTINGS,
            "tsnav": __version__,
        },
    }


def saved_results(out: Path, inputs: dict | None) -> dict | None:
    """The ``results.json`` of an earlier evaluation into ``out`` when it was made from exactly ``inputs``
    (:func:`release_inputs`), else None."""
    path = out / "results.json"
    if inputs is None or not path.exists():
        return None
    try:
        saved = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return saved if saved.get("inputs") == inputs and saved.get("rows") else None


def release_rows(
    folder: Path,
    data: Path,
    out: Path,
    protocols: list[str],
    baselines: bool = True,
    batch_size: int = 4096,
    split: str = "test",
) -> list[dict]:
    """Evaluate the shipped agent (greedy) on the test episodes of each protocol, and beside it the scripted
    explorer with the same stage switch and the random policy; each evaluation folder is kept under ``out``."""
    from ..eval.runner import evaluate_to_folder

    card = read_card(folder)
    rows = []
    for protocol in protocols:
        eps = release_episodes(data, out, protocol, split, card)
        # the card's tables: those the agent was trained with, or the detector its card swaps in
        todo = [("agent", dict(run=str(folder), checkpoint="best", detections=card["detections"]))]
        if baselines:
            todo += [
                ("scripted explorer", dict(policy="explorer", detections=card["detections"])),
                ("random", dict(policy="random")),
            ]
        for label, kw in todo:
            ev = out / protocol / label.split()[-1]
            summary = evaluate_to_folder(
                ev, data, eps, label=label, batch_size=batch_size, **protocol_kwargs(protocol), **kw
            )
            rows.append(
                {
                    "protocol": protocol,
                    "policy": label,
                    "episodes": _count(ev),
                    "metrics": {k: summary[k] for k in ("ALL", "L>=5")},
                }
            )
    return rows


def _count(ev: Path) -> int:
    return sum(1 for line in (ev / "records.jsonl").read_text().splitlines() if line.strip())


def headline(card: dict) -> str:
    """The card's figures of its evaluation split (:func:`eval_split`) in one line: the agent's SR / SPL under each
    protocol and its detector."""
    split = eval_split(card)
    rows = [r for r in card.get("figures", {}).get(split, {}).get("rows", []) if r.get("policy") == "agent"]
    if not rows:
        return f"detector {card.get('detector_shipped', '?')}; no {split} figures in its card yet"
    figs = ", ".join(
        f"{r['protocol']} {100 * r['metrics']['ALL']['SR']:.2f} / {100 * r['metrics']['ALL']['SPL']:.2f}" for r in rows
    )
    n = card["figures"][split].get("episodes", "?")
    where = f"{split}, challenge episodes" if challenge_card(card) else split
    return f"{where} SR / SPL ({n} episodes): {figs}; detector {card.get('detector_shipped', '?')}"


def format_rows(rows: list[dict]) -> str:
    """The printed table: one line per (protocol, policy), ALL and L>=5 metrics in percent."""
    head = (
        f"{'protocol':<9} {'policy':<18} {'eps':>5}  "
        + "  ".join(f"{m:>6}" for m in METRICS)
        + "   L>=5: "
        + "  ".join(f"{m:>6}" for m in ("SR", "SPL"))
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        a, l5 = r["metrics"]["ALL"], r["metrics"]["L>=5"]
        lines.append(
            f"{r['protocol']:<9} {r['policy']:<18} {r['episodes']:>5}  "
            + "  ".join(f"{100 * a[k]:6.2f}" for k in METRICS)
            + "         "
            + "  ".join(f"{100 * l5[k]:6.2f}" for k in ("SR", "SPL"))
        )
    return "\n".join(lines)


def build_parser(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    ev = sub.add_parser(
        "eval",
        help="evaluate a shipped agent on the real test rooms, a RoboTHOR agent on the val scenes' challenge "
        "episodes (builds what it needs)",
    )
    ev.add_argument(
        "--agent", default=None, help="shipped agent name or folder (default: the default one; `tsnav release list`)"
    )
    ev.add_argument(
        "--data",
        default=None,
        help="world folder for the rooms (default out/release/world-vN, N the "
        "rules version of the agent's card, out/release/world-PRESET-vN for an agent of another world than "
        "ithor-real, e.g. world-robothor-real-v1; reused; built when missing). A "
        "--data folder that does not exist is refused unless --build-world. A detector that reads finer frames "
        "than the rooms' gets them built at its side in DATA-<side>px beside it",
    )
    ev.add_argument(
        "--build-world",
        action="store_true",
        help="build the agent's rooms into --data when that folder does not exist yet",
    )
    ev.add_argument(
        "--force",
        action="store_true",
        help="evaluate again even when nothing changed since the table saved in OUT/results.json (same "
        "agent and encoder weights, rooms, detection tables, features, episode lists and settings)",
    )
    ev.add_argument(
        "--out",
        default=None,
        help="evaluation folders, episode lists and results.json (default out/release/eval/AGENT/SPLIT)",
    )
    add_shared(
        ev,
        "protocol",
        default="both",
        choices=("both", *PROTOCOLS),
        metavar=None,
        help="success protocol(s) to evaluate under (default both)",
    )
    ev.add_argument("--no-baselines", action="store_true", help="only the agent (no explorer / random rows)")
    ev.add_argument(
        "--split",
        default=None,
        choices=tuple(SPLIT_EPISODES),
        help="rooms to evaluate on (default: the card's eval_split, test for the iTHOR agents; val: the "
        "validation rooms; a RoboTHOR agent's val: the 15 val scenes and the challenge's val episodes)",
    )
    ev.add_argument(
        "--update-card",
        action="store_true",
        help="write the figures into the agent's card (card.json / card.md) as those of --split",
    )
    ev.add_argument("--workers", type=int, default=2, help="world-building processes (default 2)")
    ev.add_argument("--threads", type=int, default=2, help="torch threads for features (default 2)")
    sub.add_parser("list", help="the shipped agents and their cards' headline figures")
    pk = sub.add_parser("pack", help="make a shipped-agent folder from a training run and its encoder")
    pk.add_argument("--run", required=True, help="training run folder (config.json)")
    pk.add_argument("--checkpoint", default=None, help="checkpoint folder (default RUN/best)")
    pk.add_argument("--encoder-run", required=True, help="pretraining run folder (encoder.safetensors)")
    pk.add_argument(
        "--card",
        required=True,
        help="JSON file of the model card's fields (name, summary, world, "
        "detector_shipped, detections, figures, commands, ...)",
    )
    pk.add_argument("--out", required=True, help="folder to create (e.g. src/tsnav/agent/weights/NAME)")
    mk = sub.add_parser(
        "make",
        help="make an agent from its recipe (configs/agents/NAME.toml): world, detector "
        "tables, pretraining, features, training, selection, packing, the card's figures",
    )
    mk.add_argument("recipe", metavar="RECIPE.toml", help="the agent's recipe (tsnav.pipeline.agent_recipe)")
    mk.add_argument(
        "--work",
        required=True,
        help="work folder: world, pretraining, training, evaluations, and the "
        "packed agent WORK/agent/NAME (every step resumes)",
    )
    add_shared(
        mk, "set", help="change one setting of the recipe, e.g. --set train.updates=8 (a TOML value); repeatable"
    )
    mk.add_argument(
        "--until", choices=STEPS, default=STEPS[-1], help=f"stop after this step ({', '.join(STEPS)}; default: all)"
    )
    mk.add_argument(
        "--challenge",
        default=None,
        metavar="DIR",
        help="the RoboTHOR challenge's episode folder holding train/ (e.g. ../shared/robothor/challenge_episodes; "
        "not packaged), read when the recipe scores checkpoints on its train episodes ([scoring] episodes = "
        '"challenge-train"); instead of scoring.challenge, and not written into the resolved recipe',
    )
    mk.add_argument(
        "--replace-shipped",
        default=None,
        metavar="NAME",
        help="also install the made agent as the shipped agent NAME (src/tsnav/agent/weights/NAME, "
        "replaced); NAME must be the recipe's. Without it nothing is written into the package",
    )


def run(args: argparse.Namespace) -> int:
    if args.action == "list":
        for name, p in shipped_agents().items():
            card = read_card(p)
            print(f"{name}{' (default)' if card.get('default') else ''}: {card.get('summary', '')}")
            print(f"    {headline(card)}")
        return 0
    if args.action == "pack":
        try:
            fields = json.loads(Path(args.card).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise CommandError(f"--card {args.card}: cannot read a JSON object ({e})") from None
        missing = [k for k in CARD_REQUIRED if k not in fields]
        if missing:
            raise CommandError(f"--card {args.card}: missing fields {', '.join(missing)}")
        ck = Path(args.checkpoint) if args.checkpoint else Path(args.run) / "best"
        out = pack(args.run, ck, args.encoder_run, args.out, fields)
        print(f"wrote {out} ({sum(f.stat().st_size for f in out.rglob('*') if f.is_file()) / 1e6:.1f} MB)")
        return 0
    if args.action == "make":
        return run_make(args)
    folder = agent_folder(args.agent)
    card = read_card(folder)
    split = args.split or eval_split(card)
    split_rooms(card, split)  # a split the agent's world has
    data, out = release_folders(card, folder.name, split, args.data, args.out)
    if args.data is not None and not data.is_dir() and not args.build_world:
        raise CommandError(
            f"--data {args.data}: no such world folder (--build-world builds the agent's "
            f"{split} rooms there; without --data they go to "
            f"{release_folders(card, folder.name, split)[0]})"
        )
    protocols = list(PROTOCOLS) if args.protocol == "both" else [args.protocol]
    evaluate_agent(
        folder,
        split,
        data,
        out,
        protocols,
        baselines=not args.no_baselines,
        update_card=args.update_card,
        workers=args.workers,
        threads=args.threads,
        force=args.force,
    )
    return 0


def evaluate_agent(
    folder: Path,
    split: str,
    data: Path,
    out: Path,
    protocols: list[str],
    *,
    baselines: bool = True,
    update_card: bool = False,
    workers: int = 2,
    threads: int = 2,
    force: bool = False,
) -> list[dict]:
    """``tsnav release eval``: build what the agent in ``folder`` needs in ``data`` (rooms of ``split``, detector
    tables, features), evaluate it (and the baselines) under ``protocols`` into ``out``, print the table; with
    ``update_card`` the figures are written into the folder's card. When nothing changed since the evaluation saved
    in ``out`` (:func:`release_inputs`), its table is printed instead, unless ``force``."""
    card = read_card(folder)
    say(f"agent {folder.name}: {card.get('summary', '')}")
    saved = None if force else saved_results(out, release_inputs(folder, card, data, out, protocols, baselines, split))
    if saved is not None:
        say(
            f"nothing changed since the evaluation of {saved.get('evaluated', '?')} (same agent and encoder weights, "
            f"rooms, detection tables, features, episode lists and settings): its saved table; --force evaluates again"
        )
        rows = saved["rows"]
    else:
        from ..distributed import set_threads

        set_threads(threads)
        t0 = time.perf_counter()
        times = {}
        ensure_test_world(data, card, workers, split)
        side = detector_frames(card)  # a detector reading finer frames: the rooms again at its side, beside data
        frames = frames_folder(data, side) if side else None
        if side:
            ensure_test_world(frames, card, workers, split, image_size=side)
        times["world"] = time.perf_counter() - t0
        ensure_release_detections(data, card, split, frames=frames)
        times["detections"] = time.perf_counter() - t0 - sum(times.values())
        ensure_release_features(data, folder, card, split=split)
        times["features"] = time.perf_counter() - t0 - sum(times.values())
        rows = release_rows(folder, data, out, protocols, baselines=baselines, split=split)
        times["evaluation"] = time.perf_counter() - t0 - sum(times.values())
        res = {
            "agent": folder.name,
            "card": card.get("name"),
            "split": split,
            "rows": rows,
            "seconds": times,
            "evaluated": _dt.datetime.now().strftime("%Y-%m-%d %H:%M"),
            "inputs": release_inputs(folder, card, data, out, protocols, baselines, split),
        }
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "results.json", json.dumps(res, indent=1) + "\n")
    if update_card:
        figs = card.setdefault("figures", {})
        figs[split] = {"episodes": max(r["episodes"] for r in rows), "rows": rows}
        atomic_write_text(folder / "card.json", json.dumps(card, indent=1) + "\n")
        atomic_write_text(folder / "card.md", card_markdown(card))
        say(f"card of {folder.name}: {split} figures written")
    when = (
        f"the saved table of {saved.get('evaluated', '?')}"
        if saved is not None
        else "steps: " + ", ".join(f"{k} {v:.0f} s" for k, v in times.items())
    )
    print(
        f"\n{folder.name} on the {rooms_text(card, len(ensure_names(data, split)), split)}, greedy, "
        f"detector {card['detector_shipped']} ({when})"
    )
    trained = json.loads((folder / "config.json").read_text())["train"].get("protocol", "paper")
    for p in protocols:
        print(protocol_line(p, trained))
    print(format_rows(rows))
    print(f"{'read' if saved is not None else 'wrote'} {out / 'results.json'}")
    return rows


def run_make(args: argparse.Namespace) -> int:
    """``tsnav release make RECIPE --work DIR``: the agent of a recipe, made, packed into ``WORK/agent/NAME`` and
    evaluated on val and test (a RoboTHOR agent: on its card's ``eval_split``, the val scenes' challenge episodes)
    with the figures written into its card; installed as a shipped agent only with ``--replace-shipped NAME``."""
    work = Path(args.work)
    from .agent_recipe import SECTIONS, challenge_folder, make_agent, resolve_agent

    r = resolve_agent(apply_sets(read_recipe(args.recipe), args.set, SECTIONS), work)
    if args.replace_shipped is not None and args.replace_shipped != r.name:
        raise CommandError(
            f"--replace-shipped {args.replace_shipped}: the recipe makes {r.name!r}; name it to replace it"
        )
    challenge_folder(r, args.challenge)  # refused before any work when the recipe's scoring needs one
    work.mkdir(parents=True, exist_ok=True)
    header = f"The resolved recipe of {r.name} (tsnav release make)."
    atomic_write_text(work / "recipe.toml", dump_recipe(r.to_recipe(), header=header))
    made = make_agent(r, work, until=args.until, challenge=args.challenge)
    if STEPS.index(args.until) < STEPS.index("pack"):
        say(f"stopped after step {args.until}; the run: {made.run}")
        return 0
    folder = work / "agent" / r.name
    if not (folder / "card.json").exists():
        pack(made.run, made.checkpoint, made.encoder_run, folder, agent_card(r, made.world))
        atomic_write_text(folder / "recipe.toml", dump_recipe(r.to_recipe(), header=header))
    if args.until == "eval":
        card = read_card(folder)
        for split in ("val", "test") if eval_split(card) == "test" else (eval_split(card),):
            evaluate_agent(
                folder,
                split,
                made.world,
                work / f"release_{split}",
                list(PROTOCOLS),
                update_card=True,
                workers=r.world.workers,
                threads=r.features.threads,
            )
    if args.replace_shipped:
        install_shipped(folder, WEIGHTS / r.name)
    print(f"agent {r.name}: {folder}" + (f", installed as {WEIGHTS / r.name}" if args.replace_shipped else ""))
    return 0


def agent_card(r: AgentRecipe, world: Path) -> dict:
    """The card fields of the recipe's agent: its ``[card]`` texts, what the recipe names, and the val and test
    rooms of its ``world`` (those ``tsnav release eval`` evaluates on). An agent of a world of :data:`WORLD_EVAL`
    (RoboTHOR) gets its ``eval_split`` and ``episodes`` and the rooms of that split only (RoboTHOR has no test
    split)."""
    from ..detect.shipped import shipped_meta
    from ..world.build import BuildConfig

    how = WORLD_EVAL.get(r.world.preset, {})
    splits = (how["eval_split"],) if how else ("val", "test")

    return {
        **r.card,
        "name": r.name,
        "world_preset": r.world.preset,
        "world_version": r.world.version,
        "image_size": BuildConfig.from_preset(r.world.preset).image_size,
        "detector_shipped": r.detections.card_shipped,
        "detector_fingerprint": shipped_meta(r.detections.card_shipped)["fingerprint"],
        "detections": r.detections.card_name,
        **(
            {"trained_detector_shipped": r.detections.shipped, "trained_detections": r.detections.name}
            if r.detections.card_shipped != r.detections.shipped
            else {}
        ),
        "encoder_id": r.features.encoder,
        **how,
        **{f"{split}_rooms": ensure_names(world, split) for split in splits},
        "commands": [
            f"tsnav release make configs/agents/{r.name}.toml --work WORK_DIR"
            + (" --challenge CHALLENGE_DIR" if r.scoring.episodes == "challenge-train" else "")
            + " (recipe.toml in this folder: the resolved recipe)"
        ],
    }


def install_shipped(folder: Path, dest: Path) -> None:
    """Copy the agent ``folder`` over the shipped agent ``dest`` (assembled beside it, then renamed)."""
    tmp = dest.with_name(f".{dest.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(folder, tmp)
    old = dest.with_name(f".{dest.name}.old")
    if dest.exists():
        dest.rename(old)
    tmp.rename(dest)
    shutil.rmtree(old, ignore_errors=True)


def release_folders(
    card: dict, agent: str, split: str, data: str | None = None, out: str | None = None
) -> tuple[Path, Path]:
    """The world and evaluation folders of ``tsnav release eval``: given ones, else ``out/release/world-vN`` (the
    card's rules version, so that agents of different versions never share rooms; ``world-PRESET-vN`` for a world
    other than ``ithor-real``, e.g. ``world-robothor-real-v1``) and ``out/release/eval/AGENT/SPLIT`` (so that
    agents and splits never share episode lists or results)."""
    preset, version = card.get("world_preset", "ithor-real"), int(card.get("world_version") or 1)
    name = f"world-v{version}" if preset == "ithor-real" else f"world-{preset}-v{version}"
    world = Path(data) if data else Path("out/release") / name
    return world, Path(out) if out else Path("out/release/eval") / agent / split


def ensure_names(data: Path, split: str = "test") -> list[str]:
    from ..data.reader import list_scenes

    return [p.name for p in list_scenes(data, split=split)]
