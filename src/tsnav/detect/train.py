"""Train the learned detector on the world's own renders; resumable checkpoints; temperature scaling.

Training uses the TRAIN scenes only; batches are drawn with a generator seeded by ``(seed, step)``, so a
resumed run sees the same batches as an uninterrupted one. Optimiser: AdamW with linear warm-up and cosine
decay to ``min_lr_ratio`` x ``lr`` at ``steps`` (extending a finished run with more steps re-stretches the
remaining schedule). Augmentation: horizontal flip and per-frame colour gains. Frames are drawn uniformly, or
class-balanced by repeat-factor sampling (:attr:`DetectorTrainConfig.repeat_threshold`, :func:`repeat_factors`),
which on the `ithor-real` world raised val presence AP and reach at equal steps (BENCHMARKS.md).

Calibration: a single temperature ``T`` (Guo et al. 2017) divides the presence logits,
``score = sigmoid(logit / T)``; ``T`` minimises the mean binary cross-entropy on the VAL scenes.

Checkpoint folder (``tsnav detect --checkpoint DIR``): ``DIR/checkpoints/ckpt_<step>/``, the layout of every
trainer (:mod:`tsnav.checkpoint`; the newest two kept, a broken newest one named in one line, renamed
``.broken``, and training resumes from the one before), each holding

* ``model.safetensors``: the model's state dict (BatchNorm statistics included);
* ``optimizer.safetensors``: AdamW moment tensors (``state.<param index>.<name>``);
* ``state.json``: ``format``, ``model`` (:class:`~tsnav.detect.model.DetectorConfig`), ``train``
  (:class:`DetectorTrainConfig`), ``step``, ``temperature``, ``calibrated_step``, ``min_score``, ``history`` (loss
  terms every ``log_every`` steps), ``param_groups`` of the optimiser, ``fingerprint``, ``train_scenes`` (the scenes of
  the last training segment) and ``seen_scenes`` (every segment's, :func:`seen_scenes`).

Detector folders written before that layout (the three files at the top of ``DIR``, JSON ``detector.json``,
the checkpoint before in ``DIR/previous/``) are still read, resumed and calibrated; new checkpoints go to
``DIR/checkpoints/``.
"""

from __future__ import annotations

import hashlib
import math
import os
import time
from collections.abc import Collection
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import minimize_scalar
from tqdm import tqdm

from ..atomic import atomic_write_json
from ..checkpoint import (
    CHECKPOINTS,
    STATE_FILE,
    BrokenCheckpoint,
    list_checkpoints,
    load_tensors,
    optimizer_file,
    read_json,
    resume_newest,
    save_checkpoint as save_checkpoint_folder,
    set_aside,
    weights_digest,
)
from ..distributed import set_threads
from ..errors import from_fields
from ..schedule import warmup_cosine
from .data import FrameSet, load_frames, make_batch
from .model import DetectorConfig, GridDetector, LossWeights, detection_loss


FORMAT = "tsnav-detector"


@dataclass
class DetectorTrainConfig:
    """Training of the learned detector (CPU-sized defaults: about 0.1 s per step on one core, a few
    minutes for the demo world)."""

    steps: int = 2500
    """Optimiser steps."""
    batch_size: int = 64
    """Frames per step."""
    lr: float = 2e-3
    """Peak learning rate of AdamW."""
    min_lr_ratio: float = 0.05
    """Final learning rate as a share of ``lr`` (cosine decay)."""
    warmup: int = 100
    """Linear warm-up steps."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    flip_prob: float = 0.5
    """Probability of a horizontal flip per frame."""
    color_jitter: float = 0.2
    """Colour augmentation: each frame's channels are scaled by independent factors in ``1 +- color_jitter``
    (object materials vary per instance, so colour alone must not identify a class); 0 disables it."""
    brightness: float = 0.2
    """Colour augmentation: each frame is also scaled by a factor in ``1 +- brightness``."""
    loss: LossWeights = field(default_factory=LossWeights)
    """Weights of the loss terms."""
    seed: int = 0
    """Seed of initialisation, batches and flips."""
    checkpoint_every: int = 250
    """Steps between checkpoints (and always at the end or on interruption)."""
    log_every: int = 50
    """Steps between entries of the loss history."""
    max_states_per_scene: int | None = None
    """Use at most this many (random) states per train scene; None uses all."""
    repeat_threshold: float = 0.0
    """Class-balanced sampling of the training frames (repeat-factor sampling, Gupta et al. 2019, LVIS): a frame
    is drawn with weight ``max(1, max over the classes in view of sqrt(t / f_c))``, ``f_c`` the share of the
    loaded training frames that show class ``c`` (:func:`repeat_factors`), so frames with rare classes (a phone,
    an alarm clock) come more often; 0 draws frames uniformly (the behaviour before this field). Given nonzero
    for an existing checkpoint, it replaces the stored value from the checkpoint's step on (a fine-tune)."""
    hard_negative_weight: float = 0.0
    """Hard-negative sampling (issue 23: the switch's false positives): when positive, the frames on which the
    model, as it stands when this weight is first given, scores some class with no pixel in view above
    ``hard_negative_threshold`` (:func:`hard_negative_rows`, with the checkpoint's temperature when it is
    calibrated at that step) are drawn ``hard_negative_weight`` times as often as before (on top of
    ``repeat_threshold``'s weights). The mined rows are kept in the checkpoint folder (``hard_negatives.json``,
    :func:`mined_hard_negatives`), so a resumed run draws the same batches. Given for an existing checkpoint it
    applies from that checkpoint's step on; 0 keeps the checkpoint's own setting."""
    hard_negative_threshold: float = 0.5
    """Score above which a class with no pixel in view makes a frame a hard negative."""
    threads: int = 1
    """torch CPU threads. One is the safe default: on a busy machine two threads were measured 30x slower
    per step than one (threads spin waiting for each other)."""

    @classmethod
    def from_dict(cls, d: dict) -> "DetectorTrainConfig":
        d = dict(d)
        if isinstance(d.get("loss"), dict):
            d["loss"] = LossWeights(**d["loss"])
        return from_fields(cls, d, "train config")


def default_train_steps(image_size: int) -> int:
    """Training steps ``tsnav detect`` gives a new checkpoint for ``image_size`` px frames: 9000 from 128px on
    (the `ithor-real` detector of BENCHMARKS.md), else :attr:`DetectorTrainConfig.steps`."""
    return 9000 if image_size >= 128 else DetectorTrainConfig.steps


def lr_at(step: int, cfg: DetectorTrainConfig) -> float:
    """Learning rate of optimiser step ``step`` (0-based): warm-up, then cosine to ``min_lr_ratio * lr``
    (:func:`tsnav.schedule.warmup_cosine`)."""
    return warmup_cosine(step, cfg.steps, cfg.lr, cfg.warmup, cfg.min_lr_ratio * cfg.lr)


def repeat_factors(present: np.ndarray, threshold: float) -> np.ndarray:
    """``(N,)`` float64 sampling weight of each training frame under repeat-factor sampling with threshold
    ``threshold`` (:attr:`DetectorTrainConfig.repeat_threshold`): ``max(1, max_c sqrt(threshold / f_c))`` over
    the classes ``c`` in view in the frame (``present`` ``(N, C)`` bool), ``f_c = present[:, c].mean()``; frames
    with no class in view weigh 1."""
    present = np.asarray(present, dtype=bool)
    if present.ndim != 2:
        raise ValueError(f"present must be (frames, classes), got shape {present.shape}")
    if not threshold >= 0:
        raise ValueError(f"repeat threshold must be >= 0, got {threshold}")
    freq = present.mean(axis=0) if len(present) else np.zeros(present.shape[1])
    per_class = np.ones(present.shape[1])
    seen = freq > 0
    per_class[seen] = np.maximum(1.0, np.sqrt(threshold / freq[seen]))
    return np.where(present, per_class[None, :], 1.0).max(axis=1, initial=1.0)


def repeat_factors_reference(present, threshold: float) -> np.ndarray:
    """Loop reference of :func:`repeat_factors` (same result, one frame and class at a time)."""
    present = np.asarray(present, dtype=bool)
    n, k = present.shape
    out = np.ones(n)
    for c in range(k):
        f = present[:, c].sum() / n
        if f == 0:
            continue
        r = max(1.0, math.sqrt(threshold / f))
        for i in range(n):
            if present[i, c]:
                out[i] = max(out[i], r)
    return out


def classes_with_pixels(frames: "FrameSet") -> np.ndarray:
    """``(N, C)`` bool: some object of the class has at least one pixel in the frame (``obj_state`` > 0), so a
    high score there is not a hallucination even when the object is too small to count as present."""
    seen = np.zeros(frames.present.shape, bool)
    rows, cols = np.nonzero(frames.obj_state > 0)
    cat = frames.obj_category[rows, cols].astype(np.int64)
    ok = cat >= 0
    seen[rows[ok], cat[ok]] = True
    return seen | frames.present


def hard_negative_rows(scores: np.ndarray, seen: np.ndarray, threshold: float) -> np.ndarray:
    """``(N,)`` bool: frames where some class with no pixel in view (``~seen``) scores above ``threshold``."""
    scores = np.asarray(scores)
    seen = np.asarray(seen, dtype=bool)
    if scores.shape != seen.shape:
        raise ValueError(f"scores {scores.shape} and classes in view {seen.shape} differ in shape")
    return ((scores > threshold) & ~seen).any(axis=1)


def hard_negative_rows_reference(scores, seen, threshold: float) -> np.ndarray:
    """Loop reference of :func:`hard_negative_rows`."""
    n, k = np.asarray(scores).shape
    out = np.zeros(n, bool)
    for i in range(n):
        for c in range(k):
            if not seen[i][c] and scores[i][c] > threshold:
                out[i] = True
    return out


#: File of a detector folder holding the mined hard-negative rows (:attr:`DetectorTrainConfig.hard_negative_weight`).
HARD_NEGATIVES = "hard_negatives.json"


def _frames_id(frames: "FrameSet") -> dict:
    """What identifies a training frame set in ``hard_negatives.json``: its scenes, their row ranges, and a digest of
    its ground truth (so a world rendered anew with the same state counts does not pass for the old one)."""
    digest = hashlib.sha256()
    for a in (frames.present, frames.obj_state, frames.obj_category):
        digest.update(np.ascontiguousarray(a).tobytes())
    return {
        "scenes": list(frames.scenes),
        "offsets": [int(x) for x in frames.offsets],
        "ground_truth": digest.hexdigest()[:16],
    }


def mined_hard_negatives(
    ckpt: Path,
    model: GridDetector,
    meta: dict,
    frames: "FrameSet",
    threshold: float,
    start: int,
    batch_size: int = 256,
    progress: bool = False,
) -> np.ndarray:
    """The hard-negative rows of ``frames`` (``(N,)`` bool) of the hard-negative sampling that began at step
    ``meta["hard_negatives_step"]``.

    A run that begins it now (no such step in ``meta``) mines the rows with ``model`` (scores at the checkpoint's
    temperature when it is calibrated at this step, else 1), writes them to ``ckpt/hard_negatives.json`` and
    records ``start`` in ``meta``. A resumed run reads them back; a record that is missing, damaged, of another
    step, threshold or frame set raises :class:`BrokenCheckpoint` naming the file, so a resumed run never draws
    other batches than the uninterrupted one."""
    path = Path(ckpt) / HARD_NEGATIVES
    began = meta.get("hard_negatives_step")
    if began is not None:
        rec = read_json(path) if path.exists() else None
        if rec is None:
            raise BrokenCheckpoint(
                f"{path}: missing; the hard-negative sampling of this checkpoint began at step "
                f"{began} and its rows are needed to resume it"
            )
        ident = _frames_id(frames)
        if rec.get("step") != began or rec.get("threshold") != threshold or {k: rec.get(k) for k in ident} != ident:
            raise BrokenCheckpoint(
                f"{path}: mined for another step, threshold or frame set than this run's "
                f"(step {rec.get('step')} threshold {rec.get('threshold')} against {began}, "
                f"{threshold})"
            )
        rows = np.asarray(rec.get("rows", []))
        if rows.ndim != 1 or (
            rows.size and (rows.dtype.kind not in "iu" or rows.min() < 0 or rows.max() >= len(frames))
        ):
            raise BrokenCheckpoint(f"{path}: its rows are not frame indices below {len(frames)}")
        hard = np.zeros(len(frames), bool)
        hard[rows.astype(np.int64)] = True
        return hard
    t = float(meta.get("temperature", 1.0)) if meta.get("calibrated_step") == meta.get("step") else 1.0
    chunks = []
    for a in tqdm(range(0, len(frames), 4096), desc="mining hard negatives", unit="chunk", disable=not progress):
        logits = predict(model, frames.images[a : a + 4096], batch_size)[0]
        chunks.append(1.0 / (1.0 + np.exp(-logits.astype(np.float64) / t)))
    hard = hard_negative_rows(np.concatenate(chunks), classes_with_pixels(frames), threshold)
    _atomic_json(
        path,
        {
            "format": "tsnav-hard-negatives",
            "step": int(start),
            "threshold": threshold,
            "temperature": t,
            **_frames_id(frames),
            "count": int(hard.sum()),
            "rows": np.flatnonzero(hard).tolist(),
        },
    )
    meta["hard_negatives_step"] = int(start)
    return hard


def batch_plan(
    step: int, n: int, cfg: DetectorTrainConfig, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row indices ``(B,)``, flip flags ``(B,)``, colour gains ``(B, 3)``) of step ``step``: a function of
    ``(seed, step)`` (and ``weights``) only, so a resumed run sees the same batches. Rows are drawn uniformly, or
    with replacement in proportion to ``weights`` ``(n,)`` (:func:`repeat_factors`) when given."""
    rng = np.random.default_rng([cfg.seed, step])
    if weights is None:
        idx = rng.integers(0, n, cfg.batch_size)
    else:
        idx = sample_weighted(rng.random(cfg.batch_size), weights)
    flip = rng.random(cfg.batch_size) < cfg.flip_prob
    gains = rng.uniform(1 - cfg.color_jitter, 1 + cfg.color_jitter, (cfg.batch_size, 3)) * rng.uniform(
        1 - cfg.brightness, 1 + cfg.brightness, (cfg.batch_size, 1)
    )
    return idx, flip, gains.astype(np.float32)


def sample_weighted(u: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Rows drawn in proportion to ``weights`` (non-negative, positive sum) by the uniform numbers ``u`` in
    [0, 1): row ``i`` is chosen when ``u * sum(weights)`` falls in ``[cum[i-1], cum[i])`` of the cumulative sum."""
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim != 1 or len(weights) == 0 or (weights < 0).any() or not weights.sum() > 0:
        raise ValueError("sampling weights must be a non-empty vector of non-negative numbers with a positive sum")
    cum = np.cumsum(weights)
    return np.minimum(np.searchsorted(cum, np.asarray(u) * cum[-1], side="right"), len(cum) - 1)


def apply_gains(images: torch.Tensor, gains: np.ndarray) -> torch.Tensor:
    """uint8 frames ``[B, H, W, 3]`` scaled per frame and channel by ``gains`` ``(B, 3)``, clipped to
    [0, 255] (float)."""
    return (images.float() * torch.from_numpy(gains)[:, None, None, :]).clamp(0, 255)


# ---------------------------------------------------------------------------------------------- checkpoints
def _atomic_json(path: Path, obj) -> None:
    atomic_write_json(path, obj, indent=1, sort_keys=False)


#: JSON and files of a detector folder written before the one checkpoint layout (read, never written anew).
LEGACY_META = "detector.json"
LEGACY_FILES = ("model.safetensors", "optimizer.safetensors", LEGACY_META)
LEGACY_PREVIOUS = "previous"


def _is_legacy(p: Path) -> bool:
    return (p / LEGACY_META).exists() and (p / "model.safetensors").exists()


def _meta_file(c: Path) -> Path:
    """The JSON of one checkpoint: ``state.json`` (a ``ckpt_<step>`` folder) or the legacy ``detector.json``."""
    return c / STATE_FILE if (c / STATE_FILE).exists() else c / LEGACY_META


def checkpoint_candidates(path: str | Path) -> list[Path]:
    """Checkpoints of the detector folder ``path``, newest first: ``checkpoints/ckpt_<step>`` folders, then a
    legacy checkpoint at the top of ``path`` and its ``previous/``. A folder with a ``state.json`` of its own (a
    ``ckpt_<step>`` folder, or a copy of a shipped detector) is a checkpoint itself, after the ones trained on from
    it into its ``checkpoints/`` (a ``ckpt_<step>`` folder has none)."""
    p = Path(path)
    found = list_checkpoints(p / CHECKPOINTS)[::-1]
    if (p / STATE_FILE).exists():
        return found + [p]
    return found + [c for c in (p, p / LEGACY_PREVIOUS) if _is_legacy(c)]


def is_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` holds a detector checkpoint (either layout)."""
    return bool(checkpoint_candidates(path))


def newest_checkpoint(path: str | Path) -> Path:
    """The folder holding the newest checkpoint's files of the detector folder ``path`` (``FileNotFoundError``
    in one line when there is none)."""
    found = checkpoint_candidates(path)
    if not found:
        raise FileNotFoundError(
            f"{Path(path)}: not a detector checkpoint (no {CHECKPOINTS}/ckpt_*/{STATE_FILE} or {LEGACY_META})"
        )
    return found[0]


def _pinned(path: str | Path) -> Path:
    """The checkpoint a pinned load reads: the files at the top of ``path`` when it has them (a shipped detector's
    layout), else its newest checkpoint (a training folder used as it is)."""
    p = Path(path)
    return p if _meta_file(p).exists() else newest_checkpoint(p)


def seen_scenes(meta: dict) -> list[str]:
    """The scene names a checkpoint's ``state.json`` says it was ever trained on: ``seen_scenes``, the union over
    its training segments; a checkpoint written before that record holds only its last segment's ``train_scenes``
    (what it saw before that is unknown)."""
    return list(meta.get("seen_scenes", meta.get("train_scenes", [])))


def read_meta(path: str | Path, pinned: bool = False) -> dict:
    """The JSON of the newest checkpoint of a detector folder (``state.json``; legacy ``detector.json``), or of
    the checkpoint folder ``path`` itself (``pinned``: of the files at the top of ``path`` when it has them, as
    :func:`load_model`); one-line error when absent or malformed."""
    return _read_meta(_pinned(path) if pinned else newest_checkpoint(path))


def _read_meta(c: Path) -> dict:
    p = _meta_file(c)
    meta = read_json(p)
    if meta.get("format") != FORMAT:
        raise ValueError(f"{p}: not a {FORMAT} checkpoint")
    return meta


def save_checkpoint(path: str | Path, model: GridDetector, opt: torch.optim.Optimizer | None, meta: dict) -> Path:
    """Write the checkpoint of ``meta["step"]`` into ``path/checkpoints/ckpt_<step>/`` (module docstring;
    complete in a temporary folder, then renamed; the newest two kept). Returns its folder."""
    meta = dict(meta)
    tensors = None
    if opt is not None:
        sd = opt.state_dict()
        tensors = {
            f"state.{i}.{k}": (v if torch.is_tensor(v) else torch.tensor(v))
            for i, st in sd["state"].items()
            for k, v in st.items()
        }
        meta["param_groups"] = sd["param_groups"]
    meta["fingerprint"] = weights_fingerprint(model, meta.get("temperature", 1.0))
    return save_checkpoint_folder(
        Path(path) / CHECKPOINTS, int(meta["step"]), model.state_dict(), {"format": FORMAT}, meta, tensors
    )


def weights_fingerprint(model: GridDetector, temperature: float) -> str:
    """Identifies a trained detector: :func:`~tsnav.checkpoint.weights_digest` of its weights and temperature
    (first 16 hex digits)."""
    return "learned-" + weights_digest(model.state_dict(), extra=repr(float(temperature)).encode())[:16]


def load_model(path: str | Path, pinned: bool = False) -> tuple[GridDetector, dict]:
    """(model in eval mode, checkpoint JSON) of the newest checkpoint of a detector folder (or of a checkpoint
    folder itself); ``pinned``: of the files at the top of ``path`` when it has them, whatever was trained on from
    them (a shipped detector's folder); :class:`BrokenCheckpoint` names a file that cannot be read."""
    return _load(_pinned(path) if pinned else newest_checkpoint(path))


def _load(c: Path) -> tuple[GridDetector, dict]:
    """(model in eval mode, JSON) of the one checkpoint whose files are in the folder ``c``."""
    meta = _read_meta(c)
    model = GridDetector(DetectorConfig.from_dict(meta["model"]))
    state, _ = load_tensors(c / "model.safetensors")
    missing, unexpected = model.load_state_dict(state, strict=False)
    if missing or unexpected:
        raise ValueError(
            f"{c / 'model.safetensors'}: weights do not fit the config "
            f"(missing {missing[:2]}, unexpected {unexpected[:2]})"
        )
    return model.eval(), meta


def _read_optimizer(path: Path, meta: dict) -> dict[int, dict] | None:
    """The optimiser state of a checkpoint (``None`` when it has none)."""
    f = optimizer_file(path)
    if not f.exists() or "param_groups" not in meta:
        return None
    state: dict[int, dict] = {}
    for k, v in load_tensors(f)[0].items():
        _, i, name = k.split(".", 2)
        state.setdefault(int(i), {})[name] = v
    return state


def _set_aside(ckpt: Path, c: Path) -> None:
    """Set a broken checkpoint aside: a ``ckpt_<step>`` folder is renamed ``.broken``; the files of a legacy
    top-level checkpoint are renamed ``*.broken`` (a legacy ``previous/`` is left as it is)."""
    if c.parent.name == CHECKPOINTS:
        set_aside(c)
    elif c == ckpt:  # a legacy checkpoint, or a copy of a shipped detector (its state.json at the top)
        for name in (*LEGACY_FILES, STATE_FILE):
            if (c / name).exists():
                os.replace(c / name, c / (name + ".broken"))


def resume_state(ckpt: str | Path) -> tuple[Path, GridDetector, dict, dict[int, dict] | None] | None:
    """``(folder, model, checkpoint JSON, optimiser state)`` of the newest checkpoint of the detector folder
    ``ckpt`` that reads (:func:`checkpoint_candidates`; a broken newer one is named in one line and set aside);
    None when there is none."""
    ckpt = Path(ckpt)

    def load(c: Path):
        model, meta = _load(c)
        return model, meta, _read_optimizer(c, meta)

    found = resume_newest(
        checkpoint_candidates(ckpt), load, on_broken=lambda c: _set_aside(ckpt, c), label=lambda c: str(c)
    )
    return None if found is None else (found[0], *found[1])


# ---------------------------------------------------------------------------------------------- calibration
def fit_temperature(logits: np.ndarray, present: np.ndarray, bounds: tuple[float, float] = (0.05, 20.0)) -> float:
    """Temperature ``T`` minimising the mean binary cross-entropy of ``sigmoid(logits / T)`` against
    ``present`` (Guo et al. 2017; one scalar for all classes), searched on log T within ``bounds``."""
    z = torch.as_tensor(np.asarray(logits, dtype=np.float64)).reshape(-1)
    y = torch.as_tensor(np.asarray(present, dtype=np.float64)).reshape(-1)
    if z.numel() == 0:
        raise ValueError("cannot fit a temperature on no data")

    def nll(log_t: float) -> float:
        return float(torch.nn.functional.binary_cross_entropy_with_logits(z / math.exp(log_t), y))

    res = minimize_scalar(
        nll, bounds=(math.log(bounds[0]), math.log(bounds[1])), method="bounded", options={"xatol": 1e-5}
    )
    return float(math.exp(res.x))


@torch.no_grad()
def predict(
    model: GridDetector, images: np.ndarray, batch_size: int = 256
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(logits ``(N, C)`` float32, normalised boxes ``(N, 22, 4)`` float32, features ``(N, 22, dim)`` float32)
    of uint8 frames ``(N, H, W, 3)``, in batches, in eval mode."""
    model.eval()
    n = len(images)
    D = model.cfg.dim
    logits = np.empty((n, model.cfg.num_classes), np.float32)
    boxes = np.empty((n, model.cfg.num_classes, 4), np.float32)
    feats = np.empty((n, model.cfg.num_classes, D), np.float32)
    for a in range(0, n, batch_size):
        x = model.normalize(torch.from_numpy(np.ascontiguousarray(images[a : a + batch_size])))
        lg, bx, f = model(x)
        logits[a : a + len(x)], boxes[a : a + len(x)], feats[a : a + len(x)] = lg.numpy(), bx.numpy(), f.numpy()
    return logits, boxes, feats


# ---------------------------------------------------------------------------------------------- training
@dataclass
class TrainResult:
    """What :func:`train_detector` did: ``start_step`` -> ``step``, wall seconds, last loss terms."""

    path: Path
    start_step: int
    step: int
    seconds: float
    last: dict


def train_detector(
    root: str | Path,
    ckpt: str | Path,
    train_cfg: DetectorTrainConfig | None = None,
    model_cfg: DetectorConfig | None = None,
    frames: FrameSet | None = None,
    progress: bool = True,
    scenes: Collection[str] | None = None,
    retarget: bool = False,
) -> TrainResult:
    """Train (or resume training of) the detector in checkpoint folder ``ckpt`` on the TRAIN scenes of
    ``root`` (only those named in ``scenes``, when given: cross-fitting) up to ``train_cfg.steps``. An existing
    checkpoint keeps its model and training settings except ``steps``; a finished one returns at once. ``frames``
    may pass preloaded training frames. ``retarget``: an existing checkpoint trained on frames of another side goes
    on at the train frames' side (:func:`retarget_model`); without it such frames are refused."""
    ckpt = Path(ckpt)
    train_cfg = train_cfg or DetectorTrainConfig()
    if not train_cfg.repeat_threshold >= 0:
        raise ValueError(f"repeat_threshold must be >= 0, got {train_cfg.repeat_threshold}")
    if not (train_cfg.hard_negative_weight >= 0 and math.isfinite(train_cfg.hard_negative_weight)):
        raise ValueError(f"hard_negative_weight must be a finite number >= 0, got {train_cfg.hard_negative_weight}")
    if not 0 < train_cfg.hard_negative_threshold < 1:
        raise ValueError(f"hard_negative_threshold must be in (0, 1), got {train_cfg.hard_negative_threshold}")
    set_threads(train_cfg.threads)
    model, meta, opt_state, train_cfg, start = _resume_or_start(ckpt, train_cfg, model_cfg)
    if start >= train_cfg.steps:
        return TrainResult(ckpt, start, start, 0.0, meta["history"][-1] if meta["history"] else {})
    if frames is None:
        frames = load_frames(root, "train", train_cfg.max_states_per_scene, train_cfg.seed, progress, scenes=scenes)
    if frames.images.shape[1] != model.cfg.image_size:
        if not (retarget and start > 0):
            raise ValueError(
                f"frames are {frames.images.shape[1]}px but the detector takes {model.cfg.image_size}px"
                + ("" if start == 0 else " (--retarget continues the checkpoint at the frames' size)")
            )
        model = retarget_model(model, meta, int(frames.images.shape[1]), start)
    if frames.present.shape[1] != model.cfg.num_classes:
        raise ValueError(
            f"the train scenes have {frames.present.shape[1]} target classes but the detector scores "
            f"{model.cfg.num_classes} (class set {model.cfg.class_set})"
        )
    weights = repeat_factors(frames.present, train_cfg.repeat_threshold) if train_cfg.repeat_threshold > 0 else None
    if train_cfg.hard_negative_weight > 0:
        hard = mined_hard_negatives(
            ckpt, model, meta, frames, train_cfg.hard_negative_threshold, start, progress=progress
        )
        base = np.ones(len(frames)) if weights is None else weights
        weights = base * np.where(hard, train_cfg.hard_negative_weight, 1.0)
        meta["hard_negatives"] = int(hard.sum())
    meta.setdefault("history", [])
    opt = torch.optim.AdamW(model.parameters(), lr=train_cfg.lr, weight_decay=train_cfg.weight_decay)
    if start > 0 and opt_state is not None:
        opt.load_state_dict({"state": opt_state, "param_groups": meta["param_groups"]})
    meta["train"] = asdict(train_cfg)
    meta["seen_scenes"] = sorted(set(seen_scenes(meta)) | set(frames.scenes))
    meta["train_scenes"] = frames.scenes
    model.train()
    t0 = time.perf_counter()
    step = start
    last: dict = {}
    bar = tqdm(
        total=train_cfg.steps,
        initial=start,
        desc="detector train",
        unit="step",
        disable=not progress,
        dynamic_ncols=True,
    )

    def save() -> None:
        meta["step"] = step
        save_checkpoint(ckpt, model, opt, meta)

    try:
        while step < train_cfg.steps:
            idx, flip, gains = batch_plan(step, len(frames), train_cfg, weights)
            b = make_batch(frames, idx, flip)
            for g in opt.param_groups:
                g["lr"] = lr_at(step, train_cfg)
            x = model.normalize(apply_gains(b.images, gains))
            loss, terms = detection_loss(model, x, b.present, b.obj_boxes, b.obj_category, b.obj_state, train_cfg.loss)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            last = terms
            if step % train_cfg.log_every == 0 or step == train_cfg.steps:
                meta["history"].append({"step": step, **{k: round(v, 5) for k, v in terms.items()}})
            bar.update(1)
            bar.set_postfix(loss=f"{terms['loss']:.3f}", bce=f"{terms['bce']:.3f}", giou=f"{terms['giou']:.3f}")
            if step % train_cfg.checkpoint_every == 0 and step < train_cfg.steps:
                save()
    except KeyboardInterrupt:
        save()
        raise
    finally:
        bar.close()
    save()
    model.eval()
    return TrainResult(ckpt, start, step, time.perf_counter() - t0, last)


def retarget_model(model: GridDetector, meta: dict, image_size: int, step: int) -> GridDetector:
    """``model`` for frames of ``image_size`` px: the same weights in a model whose output grid is the new side's
    (the network is convolutional, so its weights take any side that is a multiple of 8 x stem). The presence logit
    is a logsumexp over the cells plus a class bias; with ``k`` times as many cells the bias is lowered by
    ``log k``, so that cells firing as before give the presence logit they gave. ``meta`` gets the new ``model``
    config and a ``size_changes`` entry ``{"step", "from", "to"}``; the parameters keep their order and shapes,
    so an optimiser state still fits. ``ValueError`` in one line for a side the stem cannot take."""
    old = model.cfg
    cfg = DetectorConfig.from_dict({**old.to_dict(), "image_size": int(image_size)})
    new = GridDetector(cfg)  # validates the side against the stem
    state = model.state_dict()
    state["class_bias"] = state["class_bias"] - 2.0 * math.log(cfg.grid / old.grid)
    new.load_state_dict(state)
    meta["model"] = cfg.to_dict()
    meta.setdefault("size_changes", []).append({"step": int(step), "from": int(old.image_size), "to": int(image_size)})
    return new.train(model.training)


def _resume_or_start(ckpt: Path, train_cfg: DetectorTrainConfig, model_cfg: DetectorConfig | None):
    """``(model, meta, optimizer state or None, train config, start step)``: the checkpoint's, keeping its settings
    except ``steps`` and ``threads`` (and a new ``repeat_threshold``, hard-negative sampling or loss weights other than
    the defaults, recorded in ``sampling_changes`` / ``loss_changes``), or a fresh
    model at step 0."""
    found = resume_state(ckpt)
    opt_state = None
    if found is not None:
        _, model, meta, opt_state = found
        stored = DetectorTrainConfig.from_dict(meta["train"])
        stored.steps, stored.threads = train_cfg.steps, train_cfg.threads
        start = int(meta["step"])
        if train_cfg.repeat_threshold > 0 and train_cfg.repeat_threshold != stored.repeat_threshold:
            stored.repeat_threshold = train_cfg.repeat_threshold
            meta.setdefault("sampling_changes", []).append(
                {"step": start, "repeat_threshold": train_cfg.repeat_threshold}
            )
        if train_cfg.loss != LossWeights() and train_cfg.loss != stored.loss:
            stored.loss = train_cfg.loss
            meta.setdefault("loss_changes", []).append({"step": start, **asdict(train_cfg.loss)})
        hard = (train_cfg.hard_negative_weight, train_cfg.hard_negative_threshold)
        if hard[0] > 0 and hard != (stored.hard_negative_weight, stored.hard_negative_threshold):
            stored.hard_negative_weight, stored.hard_negative_threshold = hard
            meta.setdefault("sampling_changes", []).append(
                {"step": start, "hard_negative_weight": hard[0], "hard_negative_threshold": hard[1]}
            )
            meta.pop("hard_negatives_step", None)  # a new setting mines its rows anew, at this step
        train_cfg = stored
    else:
        if model_cfg is None:
            model_cfg = DetectorConfig()
        torch.manual_seed(train_cfg.seed)
        model = GridDetector(model_cfg)
        meta = {
            "format": FORMAT,
            "model": model_cfg.to_dict(),
            "step": 0,
            "temperature": 1.0,
            "calibrated_step": -1,
            "min_score": 0.05,
            "history": [],
        }
        start = 0
    return model, meta, opt_state, train_cfg, start


def val_is_benchmark(root: str | Path) -> bool:
    """Whether the val scenes of the world at ``root`` are its benchmark: a world without test scenes
    (``robothor-real``, evaluated on the challenge's val episodes) is, and nothing, a detector's temperature
    included, may be fitted on them (:func:`calibrate` refuses with :class:`BenchmarkSplit`)."""
    from ..data.reader import list_scenes

    return not list_scenes(root, "test")


class BenchmarkSplit(ValueError):
    """:func:`calibrate` was asked to fit on the val scenes of a world whose benchmark they are."""


def calibrate(
    root: str | Path,
    ckpt: str | Path,
    split: str = "val",
    frames: FrameSet | None = None,
    batch_size: int = 256,
    progress: bool = False,
) -> float:
    """Fit the temperature of the checkpoint on ``split`` and store it (``temperature``, ``calibrated_step``);
    returns T. Skipped (T kept) when the checkpoint was already calibrated at its current step. Refuses
    (:class:`BenchmarkSplit`, nothing written) the val scenes of a world without test scenes (:func:`val_is_benchmark`)."""
    model, meta = load_model(ckpt)
    if meta.get("calibrated_step") == meta["step"] and frames is None:
        return float(meta["temperature"])
    if frames is None:
        if split == "val" and val_is_benchmark(root):
            raise BenchmarkSplit(
                "this world has no test scenes, so its val scenes are the benchmark and nothing is fitted on them"
            )
        frames = load_frames(root, split, progress=progress)
    logits, _, _ = predict(model, frames.images, batch_size)
    t = fit_temperature(logits, frames.present)
    meta["temperature"], meta["calibrated_step"], meta["calibration_split"] = t, meta["step"], split
    meta["fingerprint"] = weights_fingerprint(model, t)
    _atomic_json(_meta_file(newest_checkpoint(ckpt)), meta)
    return t
