"""The encoder registry: each image encoder tsnav can train or load, by name (paper III-C, Table III).

An encoder is named once, here, with everything the pipeline asks of it: how to pretrain it (the
``tsnav pretrain --method`` it is made by, and that method's recipe: depth head, crop, labels, learning rate),
which architecture holds its weights (:mod:`tsnav.pretrain.archs`: how to build, save, load and describe it),
and, for the experiments' rows, its feature spec (a pretraining run, or weights the user gives). Torch-free,
so that reports and the command line read it without loading torch.

=============  ===============  ========  ==================================================================
encoder id     method           arch      what
=============  ===============  ========  ==================================================================
``demae``      ``demae``        vit       DE-MAE: RGB + depth heads, flip only (the paper's)
``mae``        ``mae``          vit       standard MAE: no depth head
``demae-crop`` ``demae-crop``   vit       DE-MAE with random resized crop (Table III's "w/ crop")
``resnet18``   ``resnet18-sup`` resnet18  ResNet18 supervised on visible categories (or ``--resnet18-weights``)
``vc1``        (none)           vit       published ViT-B weights (``--vc1-weights``)
=============  ===============  ========  ==================================================================

:func:`register_encoder` adds one (``docs/howto/add-an-encoder.md``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class EncoderKind:
    """One image encoder: how it is pretrained and which architecture loads it."""

    id: str
    """The name experiment rows use (``Row.encoder``) and the pretraining run's folder under ``pretrain/``."""
    arch: str
    """Architecture of its weights, a key of :data:`tsnav.pretrain.archs.ENCODER_ARCHS` (``vit``, ``resnet18``)."""
    doc: str
    """One line: what it is."""
    method: str | None = None
    """``tsnav pretrain --method`` that trains it (``PretrainConfig.method``); None: only given weights."""
    depth: bool = False
    """Pretraining reconstructs depth too (DE-MAE's depth head, III-C)."""
    crop: bool = False
    """Pretraining augments with random resized crops (Table III's "w/ crop")."""
    labels: bool = False
    """Pretraining is supervised: the network classifies the visible target categories of each frame."""
    base_lr: float = 1.5e-4
    """Learning rate per 256 images when ``PretrainConfig.base_lr`` is None."""
    own_steps: bool = False
    """At an experiment scale, pretrain for ``ScaleConfig.resnet_pretrain_steps`` (when set) and at this
    method's ``base_lr``, not the scale's MAE settings."""
    label: str = ""
    """Name in messages (the id when empty)."""
    weights_option: str | None = None
    """``ExperimentConfig`` field naming weights to use instead of pretraining (``resnet18_weights``), or that
    the encoder needs (``vc1_weights``); its value is read as ``<arch>:PATH``."""

    @property
    def pretrained(self) -> bool:
        """Whether tsnav trains it (has a method)."""
        return self.method is not None


#: Every encoder by id, in the order tables list them.
ENCODERS: dict[str, EncoderKind] = {}


class _Methods(Sequence):
    """Names of the pretraining methods of the registered encoders (a live, read-only view)."""

    def _names(self) -> tuple[str, ...]:
        return tuple(k.method for k in ENCODERS.values() if k.method is not None)

    def __getitem__(self, i):
        return self._names()[i]

    def __len__(self) -> int:
        return len(self._names())

    def __eq__(self, other) -> bool:
        return self._names() == tuple(other) if isinstance(other, (tuple, list, _Methods)) else NotImplemented

    def __hash__(self):
        return hash(self._names())

    def __repr__(self) -> str:
        return repr(self._names())


#: ``tsnav pretrain --method`` choices.
METHODS = _Methods()


def register_encoder(kind: EncoderKind) -> EncoderKind:
    """Add an encoder (its ``arch`` must be registered in :mod:`tsnav.pretrain.archs` before it is built)."""
    if not isinstance(kind, EncoderKind):
        raise ValueError(f"{kind!r} is not an EncoderKind")
    old = ENCODERS.get(kind.id)
    if old is not None and old != kind:
        raise ValueError(f"encoder {kind.id!r} is already registered")
    if kind.method is not None and kind.method in METHODS and method_kind(kind.method).id != kind.id:
        raise ValueError(f"pretraining method {kind.method!r} already makes encoder {method_kind(kind.method).id!r}")
    ENCODERS[kind.id] = kind
    return kind


def method_kind(method: str) -> EncoderKind:
    """The encoder a pretraining method makes; ``ValueError`` naming the choices otherwise."""
    for k in ENCODERS.values():
        if k.method == method:
            return k
    raise ValueError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")


def encoder_kind(encoder_id: str) -> EncoderKind:
    """The registered encoder ``encoder_id``; ``ValueError`` naming the choices otherwise."""
    if encoder_id not in ENCODERS:
        raise ValueError(f"unknown encoder {encoder_id!r} (choose from {', '.join(ENCODERS)})")
    return ENCODERS[encoder_id]


def describe_pretraining(cfg: dict) -> str:
    """A few words on a pretraining run's network from its saved ``PretrainConfig`` fields (for reports)."""
    method = cfg.get("method")
    kind = next((k for k in ENCODERS.values() if k.method == method), None)
    if kind is not None and kind.arch == "resnet18":
        return "ResNet18"
    if kind is not None and kind.arch != "vit":
        return kind.arch
    return f"{cfg.get('model')}, patch {cfg.get('patch_size')}"


for _k in (
    EncoderKind("demae", "vit", "DE-MAE: RGB + depth heads, flip only (III-C)", method="demae", depth=True),
    EncoderKind("mae", "vit", "standard MAE: no depth head", method="mae"),
    EncoderKind(
        "demae-crop",
        "vit",
        "DE-MAE with random resized crop (Table III's w/ crop)",
        method="demae-crop",
        depth=True,
        crop=True,
    ),
    EncoderKind(
        "resnet18",
        "resnet18",
        "ResNet18 supervised on the visible target categories (the baseline)",
        method="resnet18-sup",
        labels=True,
        base_lr=1e-3,
        own_steps=True,
        weights_option="resnet18_weights",
    ),
    EncoderKind("vc1", "vit", "published ViT-B weights (VC-1 layout)", label="VC-1", weights_option="vc1_weights"),
):
    register_encoder(_k)
