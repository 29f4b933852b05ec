"""Steps an experiment's jobs share, each made once and reused (resumable): detection tables, episode
lists, pretrained encoders and their feature caches (see :mod:`tsnav.pipeline.experiment`)."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

from ..data.detections import detections_path, read_fingerprint, write_detections
from ..data.reader import list_scenes, load_scene
from ..detect.oracle import OracleConfig, oracle_detections
from ..errors import CommandError
from ..protocol import DEFAULT_PROTOCOL, protocol_of
from ..pretrain.encoders import encoder_kind
from ..pretrain.features import cache_features, load_encoder
from ..distributed import resolve_device, trim_memory
from ..scene_pool import default_workers
from ..pretrain.train import PretrainConfig, train
from ..sim.batch import SceneBank
from ..sim.episodes import class_set_meta, make_episodes, read_episodes, write_episodes
from ..world.build import build_dataset
from .detector_steps import complete_tables, ensure_learned_detections, ensure_shipped_detections
from .config import ExperimentConfig, ScaleConfig


def say(msg: str) -> None:
    print(msg, flush=True)


def ensure_world(data: str | Path, preset: str, build: bool = False, workers: int | None = None) -> str:
    """The world preset of the dataset at ``data`` (from its ``index.json``); with ``build``, ``preset`` (the
    scale's world, ``ScaleConfig.world``) is first built there when the folder does not exist. Prints a note
    when the dataset holds another world than ``preset``."""
    root = Path(data)
    if build and not root.exists():
        say(f"building the {preset} world into {root} (resumable; interrupt and rerun to continue)")
        build_dataset(root, preset, workers=workers or min(2, os.cpu_count() or 1))
    try:
        built = json.loads((root / "index.json").read_text()).get("preset", "custom")
    except (OSError, ValueError, AttributeError):
        built = "unknown"
    if built != preset:
        say(f"note: {root} holds the {built!r} world; this scale stands for {preset!r} (tsnav world --preset {preset})")
    return built


def ensure_oracle_detections(data: str | Path, name: str = "oracle") -> int:
    """Write the oracle detector's table ``detections_<name>.hdf5`` into every scene lacking one made by the same
    oracle configuration; a table of an older oracle configuration or layout version (another ``oracle-``
    fingerprint, e.g. one whose features held the true distance) is recomputed, one made by another detector
    is refused. Returns the number of scenes written."""
    cfg = OracleConfig()
    fp = cfg.fingerprint()
    n = 0
    for p in list_scenes(data):
        have = read_fingerprint(p, name)
        if have == fp:
            continue
        if have is not None and not have.startswith("oracle-"):
            raise ValueError(
                f"{p / f'detections_{name}.hdf5'} was made by another detector ({have}); "
                f"remove it or use another --detections name"
            )
        write_detections(p, name, oracle_detections(load_scene(p), cfg))
        n += 1
    return n


def ensure_detections(
    data: str | Path,
    name: str,
    detector_dir: str | Path | None = None,
    scale: ScaleConfig | None = None,
    shipped: bool = False,
    train_root: str | Path | None = None,
    workers: int | None = None,
) -> dict:
    """Every scene's table ``detections_<name>.hdf5``; returns ``{"fingerprint", "written"}``. Oracle tables are
    computed when missing; any other name is a learned detector's table: used as it is when every scene holds one
    of the same detector (from the source asked for: :func:`~tsnav.pipeline.detector_steps.complete_tables`), else the
    detector in ``detector_dir`` is trained at ``scale`` on the train rooms of ``train_root`` (default ``data``)
    and writes the missing ones (:func:`tsnav.pipeline.detector_steps.ensure_learned_detections`; without a
    ``detector_dir`` every scene must already have its table). ``shipped``: the missing learned tables are written
    by the detector that comes with tsnav (:mod:`tsnav.detect.shipped`) instead, nothing trained. ``workers``:
    processes writing the learned tables, one thread each (None: every core, :func:`tsnav.scene_pool.default_workers`;
    the same tables for every value)."""
    workers = default_workers() if workers is None else workers
    if name == "oracle":
        n = ensure_oracle_detections(data, name)
        if n:
            say(f"detections: oracle tables written for {n} scenes")
        return {"fingerprint": OracleConfig().fingerprint(), "written": n}
    trains = detector_dir is not None and scale is not None
    if shipped or trains:
        complete_tables(data, name, "shipped" if shipped else "train")  # the one rule on foreign tables
    if shipped:
        return ensure_shipped_detections(data, name, say=say, workers=workers)
    if not trains:
        missing = [p.name for p in list_scenes(data) if not detections_path(p, name).exists()]
        if missing:
            raise CommandError(f"scene {missing[0]} has no detections_{name}.hdf5 (run `tsnav detect --name {name}`)")
        return {"fingerprint": None, "written": 0}
    done = ensure_learned_detections(data, name, detector_dir, scale, say=say, train_root=train_root, workers=workers)
    return {"fingerprint": done["fingerprint"], "written": done["written"]}


def reusable_list(path: Path, protocol: str) -> bool:
    """Whether the episode list at ``path`` exists and was made under ``protocol`` (then it is reused); a list made
    under the other protocol is a ``ValueError``: it is never replaced."""
    if not path.exists():
        return False
    have = protocol_of(read_episodes(path)[1])
    if have != protocol:
        raise ValueError(f"{path} holds episodes drawn under the {have} protocol, not {protocol}")
    return True


def ensure_episodes(
    data: str | Path,
    split: str,
    path: str | Path,
    per_room_type: int,
    seed: int = 0,
    success_distance: float = 1.0,
    protocol: str = DEFAULT_PROTOCOL,
) -> Path:
    """The fixed episode list of ``split`` at ``path`` drawn under the success ``protocol`` (made once; reused
    when present; ``ValueError`` when the file there was drawn under another protocol - it is never replaced)."""
    path = Path(path)
    if reusable_list(path, protocol):
        return path
    bank = SceneBank.from_root(data, split, success_distance=success_distance, protocol=protocol)
    eps = make_episodes(bank, per_room_type, seed)
    if not eps:
        raise ValueError(f"{data}: no valid episode in split {split!r}")
    write_episodes(
        path,
        eps,
        split=split,
        seed=seed,
        protocol=protocol,
        success_distance=success_distance,
        per_room_type=per_room_type,
        start_horizon=None,
        room_targets=True,
        data=str(Path(data).resolve()),
        **class_set_meta(bank),
    )
    return path


def ensure_challenge_episodes(
    data: str | Path,
    split: str,
    path: str | Path,
    protocol: str = DEFAULT_PROTOCOL,
    *,
    challenge: str | Path | None = None,
    scenes: list[str] | None = None,
    per_room_type: int | None = None,
    seed: int = 0,
    success_distance: float = 1.0,
) -> Path:
    """The RoboTHOR challenge's episodes of ``split`` on the scenes of ``data`` as a tsnav episode list at ``path``
    (``tsnav thor challenge-episodes``: :mod:`tsnav.sim.challenge`'s rules, what was dropped recorded), made once
    and reused (``ValueError`` when the file there was made under another protocol; it is never replaced).

    ``challenge``: the challenge's episode folder holding ``split/`` (None: the copy packaged with tsnav, val only,
    :func:`~tsnav.sim.challenge.packaged_challenge`); ``scenes``: the scene names of the bank (None: the scenes of
    ``data`` of ``split``); ``per_room_type``: a fixed sample of that many converted episodes per room type drawn
    with ``seed`` (:func:`~tsnav.sim.challenge.sample_per_room_type`; None: every converted episode)."""
    from ..sim.challenge import (
        CHALLENGE_SOURCE,
        HEADING_RULE,
        challenge_episodes,
        packaged_challenge,
        ratio_summary,
        read_challenge_episodes,
        take_sample,
    )

    path = Path(path)
    if reusable_list(path, protocol):
        return path
    root = packaged_challenge() if challenge is None else Path(challenge)
    records = read_challenge_episodes(root, split)
    paths = [Path(data) / n for n in scenes] if scenes is not None else list_scenes(data, split)
    if not paths:
        raise ValueError(f"{data}: no complete scenes in split {split!r}")
    bank = SceneBank([load_scene(p) for p in paths], success_distance=success_distance, protocol=protocol)
    eps, st = challenge_episodes(records, bank)
    say(f"challenge {split} episodes ({protocol}): {st.summary()}")
    eps, sample = take_sample(eps, per_room_type, seed)
    if not eps:
        raise ValueError(f"{data}: no episode of the challenge's {split} split could be converted")
    write_episodes(
        path,
        eps,
        split=split,
        source=CHALLENGE_SOURCE.format(split=split),
        challenge="packaged with tsnav (tsnav/world/data/robothor/challenge_episodes)"
        if challenge is None
        else str(root.resolve()),
        protocol=protocol,
        success_distance=success_distance,
        class_set=bank.class_set.name,
        start_horizon=30,
        room_targets=False,
        heading_rule=HEADING_RULE,
        data=str(Path(data).resolve()),
        conversion=st.to_json(),
        **sample,
        lengths=ratio_summary(eps),
    )
    return path


def episodes_name(split: str, protocol: str = DEFAULT_PROTOCOL) -> str:
    """File name of a shared episode list: ``{split}_episodes.json`` under ``paper`` (as before protocols),
    ``{split}_episodes_{protocol}.json`` otherwise."""
    return f"{split}_episodes.json" if protocol == DEFAULT_PROTOCOL else f"{split}_episodes_{protocol}.json"


@dataclass
class EncoderSpec:
    """How to obtain an encoder: a ``tsnav features`` spec, the ViT sizes for ``vit:``/``untrained:`` specs, and
    the pretraining run that produces it (None when nothing needs training)."""

    id: str
    spec: str
    model: str = "vit_base"
    patch_size: int = 16
    img_size: int = 224
    pretrain: PretrainConfig | dict | None = None
    """The pretraining run in ``pretrain_dir/<id>`` (or its ``PretrainConfig`` fields; None: use ``spec`` as it
    is)."""


def encoder_spec(enc: str, scale: ScaleConfig, pretrain_dir: Path, cfg: ExperimentConfig) -> EncoderSpec:
    """The :class:`EncoderSpec` of an encoder id of the rows at a scale, from the encoder registry
    (:mod:`tsnav.pretrain.encoders`): the weights its ``weights_option`` names when given (required when the
    encoder has no pretraining method), else its pretraining run ``pretrain_dir/<method>`` at the scale."""
    kind = encoder_kind(enc)
    weights = getattr(cfg, kind.weights_option) if kind.weights_option else None
    if not kind.pretrained and not weights:
        raise ValueError(f"the {kind.label or enc} row needs --{kind.weights_option.replace('_', '-')} PATH")
    if weights:
        if kind.pretrained:  # given weights replace the pretraining; the scale's input size
            return EncoderSpec(enc, f"{kind.arch}:{weights}", img_size=scale.pretrain.img_size)
        return EncoderSpec(enc, f"{kind.arch}:{weights}", "vit_base", 16, 224)
    method = kind.method
    run = pretrain_dir / method
    pre = scale.pretrain
    if kind.own_steps:  # the method's own learning rate; its own step budget when the scale names one
        steps = scale.resnet_pretrain_steps if scale.resnet_pretrain_steps is not None else pre.steps
        pre = replace(pre, steps=steps, base_lr=None)
    pre = replace(pre, method=method, device=cfg.device)
    return EncoderSpec(enc, str(run), pre.model, pre.patch_size, pre.img_size, pre)


def ensure_encoder(es: EncoderSpec, data: str | Path) -> None:
    """Run (or resume, or skip when finished) the pretraining run of ``es``."""
    if es.pretrain is None:
        return
    pre = es.pretrain if isinstance(es.pretrain, PretrainConfig) else PretrainConfig(**es.pretrain)
    say(f"pretrain {pre.method} -> {es.spec}")
    res = train(pre, data, es.spec, progress=True)
    trim_memory()  # the training images are freed: hand their memory back before the next stages
    if not res["finished"]:
        raise RuntimeError(f"pretraining {es.spec} did not finish")


def ensure_features(
    es: EncoderSpec,
    data: str | Path,
    splits: list[str],
    batch_size: int = 128,
    device: str = "auto",
    workers: int | None = None,
) -> str:
    """Cache the features of ``es`` for the scenes of ``splits``; returns the cache name
    ``<id>-<fingerprint>`` (identical encoders share a cache). ``workers``: processes encoding the scenes on one
    thread each (:func:`~tsnav.pretrain.features.cache_features`); None: every core on a CPU
    (:func:`tsnav.scene_pool.default_workers`), this process alone on a GPU."""
    enc = load_encoder(es.spec, es.model, es.patch_size, es.img_size, resolve_device(device))
    if workers is None:
        workers = default_workers() if enc.device.type == "cpu" else 0
    name = f"{es.id}-{enc.fingerprint[:10]}"
    for s in splits:
        cache_features(enc, data, name, batch_size=batch_size, split=s, progress=True, workers=workers)
    return name
