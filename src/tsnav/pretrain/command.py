"""``tsnav pretrain``: DE-MAE / MAE / DE-MAE w/ crop / supervised ResNet18 pretraining (paper §III-C).

Examples::

    tsnav pretrain --data data/world --out runs/demae --method demae --model vit_tiny --patch-size 16 --img-size 64 --steps 2000
    tsnav pretrain --data data/world --out runs/demae --config RECIPE.toml --set pretrain.steps=2000
    torchrun --nproc_per_node 2 -m tsnav.cli pretrain --data data/world --out runs/demae ...

Running the same command again resumes an interrupted run; a finished run is not retrained.
"""

from __future__ import annotations

import argparse
import os

from ..atomic import atomic_write_text
from ..errors import CommandError
from ..settings import add_options, add_shared, apply_sets, build, dump_recipe, given, merge, read_recipe, to_recipe
from .model import SIZES
from .train import METHODS, PretrainConfig, train

#: Option names ``tsnav pretrain`` took before its options were generated from :class:`PretrainConfig`.
ALIASES = {"patch_size": ("--patch",), "num_workers": ("--workers",)}


def build_parser(parser: argparse.ArgumentParser) -> None:
    add_shared(parser, "data", required=True, help="dataset root (scene folders; train split is used)")
    add_shared(parser, "out", required=True, help="run folder (created; resumed when it exists)")
    add_shared(
        parser,
        "config",
        help="a recipe file whose [pretrain] section sets the settings below; options given here override it",
    )
    add_shared(parser, "set", help="set one setting, e.g. --set pretrain.steps=800 (a TOML value); repeatable")
    add_shared(parser, "quiet")
    add_options(
        parser.add_argument_group("pretraining (PretrainConfig; recipe section [pretrain])"),
        PretrainConfig,
        "pretrain",
        aliases=ALIASES,
        choices={"method": METHODS, "model": sorted(SIZES)},
    )


def config_from_args(args: argparse.Namespace) -> PretrainConfig:
    recipe = apply_sets(read_recipe(args.config) if args.config else {}, args.set, ("pretrain",))
    unknown = sorted(set(recipe) - {"pretrain"})
    if unknown:
        raise CommandError(f"{args.config}: no section {', '.join(unknown)} in a pretraining recipe ([pretrain])")
    return build(PretrainConfig, merge(recipe, {"pretrain": given(args, "pretrain")}).get("pretrain"), "pretrain")


def run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    res = train(cfg, args.data, args.out, progress=not args.quiet)
    if res["finished"] and int(os.environ.get("RANK", "0")) == 0:
        loss = f"{res['loss']:.4f}" if res.get("loss") is not None else "n/a"
        print(f"pretraining done: {res['step']} steps, last loss {loss}; encoder at {args.out}/encoder.safetensors")
        atomic_write_text(
            f"{args.out}/recipe.toml",
            dump_recipe({"pretrain": to_recipe(cfg)}, header="The resolved recipe (tsnav pretrain)."),
        )
    return 0
