"""The ``tsnav`` command: one entry point, one subcommand per step of the data flow.

Each subcommand lives in its own module exposing ``build_parser(parser)`` and ``run(args) -> int``; the
module is imported only when its subcommand runs, so a missing optional dependency of one step never
breaks the others.

Errors: a user's mistake prints one line ``tsnav CMD: error: ...`` and exits with 2; a bug keeps its traceback.
A mistake is what tsnav itself refuses on purpose: a :class:`~tsnav.errors.CommandError`, a missing or
unreadable file or folder the user named (``FileNotFoundError``, ``NotADirectoryError``, ``PermissionError``,
``IsADirectoryError``), or a ``ValueError`` / ``KeyError`` raised by a ``raise`` statement of tsnav's own code
(its checks of settings and inputs). A ``ValueError`` or ``KeyError`` raised anywhere else (a failed lookup, numpy,
torch, the standard library) is a bug and is not hidden. ``tsnav --debug CMD ...`` prints the traceback of
every error. Abbreviated options are refused (``--pol`` is not ``--policy``).
"""

from __future__ import annotations

import dis
import importlib
import sys
from pathlib import Path

from .errors import CommandError
from .settings import parser as new_parser
from .settings import refuse_abbreviations

#: subcommand -> (module, one-line help)
COMMANDS = {
    "world": (
        "tsnav.world.command",
        "build an offline dataset (procedural or real rooms); `world fidelity`: check it against real trajectories",
    ),
    "show": ("tsnav.world.show", "draw a scene folder: top-down map and first-person views (PNG)"),
    "eval": ("tsnav.eval.command", "evaluate a policy or a trained run on an episode list"),
    "episodes": ("tsnav.sim.command", "write fixed validation / test episode lists (JSON)"),
    "detect": ("tsnav.detect.command", "compute per-state detections (oracle or learned detector)"),
    "pretrain": ("tsnav.pretrain.command", "pretrain a ViT encoder with DE-MAE / MAE"),
    "features": ("tsnav.pretrain.features", "cache encoder features for every state of a dataset"),
    "train": ("tsnav.rl.command", "train a navigation agent (A3C or batched A2C)"),
    "select": ("tsnav.eval.select", "choose a run's best checkpoint on validation episodes (kept as RUN/best)"),
    "convergence": ("tsnav.pipeline.convergence", "train in chunks, score each on validation episodes, plot the curve"),
    "experiment": (
        "tsnav.pipeline.experiment",
        "run one of the paper's experiments (ablation, pretraining, threshold)",
    ),
    "claims": ("tsnav.report.claims", "read finished experiments against the paper's claims (Welch tests)"),
    "report": ("tsnav.report.html", "write an HTML report for a run or experiment folder"),
    "thor": ("tsnav.thor.command", "import AI2-THOR offline data or export from a live AI2-THOR"),
    "demo": ("tsnav.pipeline.demo", "the main job: world, pretraining, detections, training, evaluation, report"),
    "release": ("tsnav.pipeline.release", "evaluate the trained agent that ships with tsnav on the real test rooms"),
    "analyze": ("tsnav.analyze.command", "the analyses behind docs/RESULTS.md (`tsnav analyze` lists them)"),
}


#: Errors about the user's own files and folders: one line (the message names the path).
PATH_ERRORS = (FileNotFoundError, NotADirectoryError, PermissionError, IsADirectoryError)
_PACKAGE = Path(__file__).resolve().parent
_RAISE = dis.opmap["RAISE_VARARGS"]


def is_mistake(e: BaseException) -> bool:
    """Whether ``e`` is a user's mistake (one line) rather than a bug (traceback); see the module docstring."""
    if isinstance(e, (CommandError, *PATH_ERRORS)):
        return True
    if not isinstance(e, (ValueError, KeyError)) or e.__traceback__ is None:
        return False
    tb = e.__traceback__
    while tb.tb_next is not None:
        tb = tb.tb_next
    code = tb.tb_frame.f_code
    raised_here = code.co_code[tb.tb_lasti] == _RAISE  # a raise statement, not a failed call or lookup
    return raised_here and _PACKAGE in Path(code.co_filename).resolve().parents


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = new_parser(prog="tsnav", description=__doc__.splitlines()[0])
    parser.add_argument("--debug", action="store_true", help="print the traceback of every error")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    debug = bool(argv) and argv[0] == "--debug"
    argv = argv[1:] if debug else argv
    if not argv or argv[0] in ("-h", "--help"):
        parser.print_help()
        return 0
    name = argv[0]
    if name not in COMMANDS:
        parser.error(f"unknown command {name!r} (choose from {', '.join(COMMANDS)})")
    module_name, help_ = COMMANDS[name]
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name and e.name.startswith("tsnav"):
            print(f"tsnav {name}: not available in this version", file=sys.stderr)
            return 2
        raise
    p = new_parser(prog=f"tsnav {name}", description=help_)
    module.build_parser(p)
    refuse_abbreviations(p)
    args = p.parse_args(argv[1:])
    try:
        return int(module.run(args) or 0)
    except Exception as e:
        if debug or not is_mistake(e):
            raise
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"tsnav {name}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"tsnav {name}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    # Run through the package module so that exception classes are the ones other modules import.
    from tsnav.cli import main as _main

    raise SystemExit(_main())
