"""One source per setting: command-line options and recipe files made from the config dataclasses.

A setting is a field of a config dataclass (:class:`~tsnav.rl.config.TrainConfig`,
:class:`~tsnav.tsrm.reward.RewardConfig`, :class:`~tsnav.agent.model.AgentConfig`, the pretraining, detector and
pipeline configs). Its type, default and documentation are written once, on the field: the docstring under the
field is its help, a class attribute ``CHOICES`` (field -> allowed values) names its choices. Everything else is
made from that (values are checked by the config itself, so its one-line message is the error whatever
the source of the value):

- :func:`add_options` turns a dataclass into command-line options ``--field-name`` (``--x`` / ``--no-x`` for a
  bool; ``none`` for a field that may be None), each in the parser's namespace under ``"<section>.<field>"``;
  :func:`given` reads back the ones the user gave. Options shared by many commands (``--data``, ``--out``,
  ``--protocol``, ``--detections``, ``--threads``, ...) are declared once in :data:`SHARED` and added with
  :func:`add_shared`; a generated option of the same name takes the shared declaration.
- A *recipe* is a TOML file of sections, one per config (``[train]``, ``[reward]``, ``[agent]``, ...):
  :func:`read_recipe` reads it (one recipe may build on another: ``extends = "OTHER.toml"``), :func:`apply_sets`
  applies ``--set section.key=value`` on top, :func:`build` turns a section into its dataclass (unknown keys and
  bad values are refused in one line naming them), and :func:`dump_recipe` writes the resolved recipe beside an
  output. TOML has no null: a value of ``"none"`` is None.
- :func:`first_difference` names the first setting where two resolved recipes differ (a resume with other
  settings is refused with it).

Adding a setting to a command is adding a documented field to its config dataclass: the option, the recipe key
and the saved resolved recipe follow. A command-only option (one that is no setting of any config) is one
``add_argument`` call in the command's ``build_parser``, with ``allow_abbrev`` off as for every parser of
``tsnav`` (:func:`parser`).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import math
import re
import textwrap
import types
import typing
from functools import lru_cache
from pathlib import Path

from .errors import CommandError

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib
from .protocol import DEFAULT_PROTOCOL, PROTOCOLS

#: The value that stands for None in a recipe file or on the command line (TOML has no null).
NONE = "none"


# ------------------------------------------------------------------------------------------------------------
# Field documentation and types
# ------------------------------------------------------------------------------------------------------------


@lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each field of dataclass ``cls`` (and of its dataclass bases), whitespace folded
    and reStructuredText roles reduced to their text; empty when the source cannot be read."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass is object:
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, nxt in zip(body, body[1:]):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(nxt, ast.Expr)
                and isinstance(nxt.value, ast.Constant)
                and isinstance(nxt.value.value, str)
            ):
                docs[node.target.id] = plain(nxt.value.value)
    return docs


def plain(doc: str) -> str:
    """A docstring as one line of plain text: ``:role:`~a.b.C``` -> ``C``, ````x```` -> ``x``."""

    def role(m: re.Match) -> str:
        text = m.group(2)
        if "<" in text:
            return text.split("<")[0].strip()
        return text.split(".")[-1] if m.group(1) else text

    doc = re.sub(r":[\w:]+:`(~?)([^`]*)`", role, doc)
    doc = doc.replace("``", "")
    return " ".join(doc.split())


def _hints(cls: type) -> dict[str, object]:
    return typing.get_type_hints(cls)


def _unwrap(tp) -> tuple[object, bool]:
    """``(type, may_be_none)`` of an annotation such as ``int | None``."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return (rest[0] if len(rest) == 1 else str), True
    return tp, False


def _scalar(tp) -> type | None:
    """The scalar Python type an option of annotation ``tp`` parses to (None: not a command-line option)."""
    tp, _ = _unwrap(tp)
    return tp if tp in (int, float, str, bool) else None


def _sequence_item(tp) -> type | None:
    """The scalar type of the items of a tuple / list annotation (``tuple``: str), else None."""
    tp, _ = _unwrap(tp)
    if (typing.get_origin(tp) or tp) not in (tuple, list):
        return None
    items = {a for a in typing.get_args(tp) if a is not Ellipsis}
    item = items.pop() if len(items) == 1 else str if not items else None
    return item if item in (int, float, str) else None


def _convert(value, tp, key: str):
    """``value`` (from TOML or the command line) as annotation ``tp`` asks; a one-line CommandError if it cannot."""
    base, optional = _unwrap(tp)
    if value is None or (isinstance(value, str) and value.lower() == NONE and (optional or base is not str)):
        if optional:
            return None
        raise CommandError(f"{key}: may not be {NONE}")
    origin = typing.get_origin(base) or base
    try:
        if base is bool:
            if isinstance(value, str) and value.lower() in ("true", "false"):
                return value.lower() == "true"
            if not isinstance(value, bool):
                raise ValueError
            return value
        if base is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if base is float:
            if isinstance(value, bool):
                raise ValueError
            return float(value)
        if base is str:
            if not isinstance(value, str):
                raise ValueError
            return value
        if origin in (tuple, list):
            if isinstance(value, str):
                value = [v.strip() for v in value.split(",") if v.strip()]
            return tuple(value) if origin is tuple else list(value)
        if origin is dict:
            if not isinstance(value, dict):
                raise ValueError
            return dict(value)
    except (TypeError, ValueError):
        raise CommandError(f"{key}: {value!r} is not a {getattr(base, '__name__', base)}") from None
    return value


# ------------------------------------------------------------------------------------------------------------
# Command-line options
# ------------------------------------------------------------------------------------------------------------


#: Options that many commands take, declared once: ``add_argument`` keywords. A command may give its own help
#: (what the folder holds, say) or default; the name, type and choices stay these.
SHARED: dict[str, dict] = {
    "data": dict(help="dataset root: the world's scene folders (`tsnav world`)"),
    "out": dict(help="output folder (created; an existing one is resumed)"),
    "features": dict(help="feature cache name: features_<NAME>.hdf5 in every scene (`tsnav features`)"),
    "detections": dict(
        help="detection tables detections_<NAME>.hdf5 (`tsnav detect`), e.g. learned or oracle; the "
        "agent never falls back to ground truth"
    ),
    "protocol": dict(
        metavar="{" + ",".join(PROTOCOLS) + "}",
        help=f"success protocol: {DEFAULT_PROTOCOL} (the target in view within "
        "1.0 m, paper III-A) or lineage (the 1.5 m visibility map, as the "
        "lineage's evaluator); recorded with every output",
    ),
    "threads": dict(type=int, help="torch CPU threads"),
    "device": dict(help="auto (CUDA when present), cpu or cuda"),
    "seed": dict(type=int, help="seed"),
    "workers": dict(type=int, help="worker processes"),
    "quiet": dict(action="store_true", help="no progress bar"),
    "config": dict(
        metavar="RECIPE.toml",
        help="a recipe file (TOML; configs/ holds the project's): its sections "
        "set the run's settings; options given here override it",
    ),
    "set": dict(
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="set one setting of the recipe (a TOML value; none for None), e.g. --set reward.k_distance=0.3; "
        "repeatable",
    ),
}


def add_shared(parser, name: str, **overrides) -> argparse.Action:
    """Add the shared option ``--name`` (:data:`SHARED`), with ``overrides`` (e.g. ``help``, ``default``,
    ``required``) of this command."""
    kw = {**SHARED[name], **overrides}
    return parser.add_argument("--" + name.replace("_", "-"), **kw)


def option_name(field: str) -> str:
    return "--" + field.replace("_", "-")


def add_options(
    parser,
    cls: type,
    section: str,
    *,
    exclude=(),
    only=None,
    prefix: str = "",
    defaults: object | None = None,
    aliases: dict | None = None,
    choices: dict | None = None,
) -> list[str]:
    """Add one option per field of dataclass ``cls`` (scalar fields; nested dataclasses flattened, their options
    named ``--<prefix><field>``) to ``parser`` (or an argument group): help from the field's docstring, choices
    from ``cls.CHOICES``, the default shown from ``defaults`` (an instance; default: ``cls()`` when it can be
    made). Every option defaults to None (not given), its value lands under ``"<section>.<field>"`` (nested:
    ``"<section>.<outer>.<field>"``). ``aliases``: field -> other option names it also answers to (names a command
    had before its options were generated); ``choices``: field -> values, beside ``cls.CHOICES``. Returns the
    fields added."""
    docs = field_docs(cls)
    choices = {**getattr(cls, "CHOICES", {}), **(choices or {})}
    if defaults is None:
        try:
            defaults = cls()
        except TypeError:
            defaults = None
    added = []
    for f in dataclasses.fields(cls):
        if f.name in exclude or (only is not None and f.name not in only) or not f.init:
            continue
        tp = _hints(cls)[f.name]
        if dataclasses.is_dataclass(_unwrap(tp)[0]):
            sub = getattr(defaults, f.name, None)
            added += [
                f"{f.name}.{n}"
                for n in add_options(parser, _unwrap(tp)[0], f"{section}.{f.name}", prefix=prefix, defaults=sub)
            ]
            continue
        base = _scalar(tp)
        item = _sequence_item(tp) if base is None else None
        if base is None and item is None:
            continue
        default = getattr(defaults, f.name, None) if defaults is not None else None
        text = docs.get(f.name, "")
        shown = NONE if default is None else repr(default) if default == "" else default
        help_ = f"{text} (default: {shown})" if text else f"(default: {shown})"
        kw: dict = dict(dest=f"{section}.{f.name}", default=None, help=help_.replace("%", "%%"))
        if f.name in SHARED and prefix == "" and SHARED[f.name].get("action") is None:
            kw.update({k: v for k, v in SHARED[f.name].items() if k == "metavar"})
        if item is not None:  # A,B,... or the option repeated
            kw.update(action="extend", type=_items_type(item, section + "." + f.name), metavar=f.name.upper())
        elif base is bool:
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw["type"] = _option_type(tp, section + "." + f.name)
            kw.setdefault("metavar", f.name.upper())
        if f.name in choices:  # shown; checked by the config itself, whose message is one line
            kw["metavar"] = "{" + ",".join(map(str, choices[f.name])) + "}"
        parser.add_argument(option_name(prefix + f.name), *(aliases or {}).get(f.name, ()), **kw)
        added.append(f.name)
    return added


def _option_type(tp, key: str):
    def parse(text: str):
        try:
            return _convert(text, tp, key)
        except CommandError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    parse.__name__ = getattr(_unwrap(tp)[0], "__name__", "value")
    return parse


def _items_type(item: type, key: str):
    def parse(text: str) -> list:
        try:
            return [_convert(x.strip(), item, key) for x in text.split(",") if x.strip()]
        except CommandError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    return parse


def given(args: argparse.Namespace, section: str) -> dict:
    """The options of ``section`` the user gave (nested sections as nested dicts)."""
    out: dict = {}
    for dest, v in vars(args).items():
        if v is None or not dest.startswith(section + "."):
            continue
        keys = dest[len(section) + 1 :].split(".")
        d = out
        for k in keys[:-1]:
            d = d.setdefault(k, {})
        d[keys[-1]] = v
    return out


class Parser(argparse.ArgumentParser):
    """An ``argparse.ArgumentParser`` that refuses abbreviated options (``--pol`` is no ``--policy``), for every
    parser and subparser of ``tsnav``."""

    def __init__(self, *args, **kwargs):
        kwargs["allow_abbrev"] = False
        super().__init__(*args, **kwargs)


def parser(**kwargs) -> argparse.ArgumentParser:
    """A :class:`Parser` (subparsers added to it are Parsers too)."""
    return Parser(**kwargs)


def refuse_abbreviations(p: argparse.ArgumentParser) -> None:
    """Turn off ``allow_abbrev`` on ``p`` and every subparser below it (parsers made by ``add_subparsers``)."""
    p.allow_abbrev = False
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                refuse_abbreviations(sub)


# ------------------------------------------------------------------------------------------------------------
# Recipes (TOML)
# ------------------------------------------------------------------------------------------------------------


#: The top-level recipe key naming the recipe a recipe builds on: a path relative to the recipe's own folder.
EXTENDS = "extends"


def _load_toml(p: Path) -> dict:
    try:
        with open(p, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise CommandError(f"{p}: no such recipe file") from None
    except tomllib.TOMLDecodeError as e:
        raise CommandError(f"{p}: not a valid TOML recipe ({e})") from None
    except OSError as e:
        raise CommandError(f"{p}: cannot read: {e}") from None


def read_recipe(path: str | Path) -> dict:
    """The recipe in TOML file ``path`` as nested dicts; a one-line CommandError naming the file and the problem.

    A recipe may build on another: ``extends = "OTHER.toml"`` (top level; relative to the recipe's folder) reads
    OTHER first (itself perhaps extending a third) and lays this file's settings over it, section by section and
    key by key (:func:`merge`); the result has no ``extends`` key. A recipe cannot take a base's setting or section
    away, only set it; it must set its own ``name`` when the base has one, and ``[card] default`` (the default
    agent) is never inherited. A chain that comes back to a file it passed through is refused."""
    return _read_recipe(Path(path), ())


def _read_recipe(p: Path, chain: tuple[Path, ...]) -> dict:
    recipe = _load_toml(p)
    base = recipe.pop(EXTENDS, None)
    if base is None:
        return recipe
    if not isinstance(base, str) or not base.strip():
        raise CommandError(f"{p}: {EXTENDS} must name a recipe file (a path relative to {p.parent}), got {base!r}")
    here = p.resolve()
    target = p.parent / base
    if target.resolve() in (*chain, here):
        loop = " -> ".join(str(x) for x in (*chain, here, target.resolve()))
        raise CommandError(f"{p}: {EXTENDS} = {base!r} comes back to a recipe it passed through ({loop})")
    if not target.exists():
        raise CommandError(f"{p}: {EXTENDS} = {base!r}: no such recipe file ({target})")
    inherited = _read_recipe(target, (*chain, here))
    if "name" in inherited and "name" not in recipe:
        raise CommandError(
            f"{p}: extends {base!r} but sets no name of its own (it would make the agent {base!r} makes)"
        )
    card = inherited.get("card")
    if isinstance(card, dict):
        card.pop("default", None)  # which agent is the default is said by its own recipe, never inherited
    return merge(inherited, recipe)


def parse_value(text: str):
    """A ``--set`` value: a TOML value (``0.3``, ``true``, ``"x"``, ``[1, 2]``), else the text as a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_sets(recipe: dict, sets: list[str], sections: tuple[str, ...] | None = None) -> dict:
    """A copy of ``recipe`` with every ``SECTION.KEY=VALUE`` of ``sets`` applied (``KEY`` may be dotted further,
    ``reward.area.near_level=0.5``); ``sections``: the sections this command knows (others refused)."""
    out = _copy(recipe)
    for item in sets:
        key, sep, value = item.partition("=")
        parts = key.strip().split(".")
        if not sep or len(parts) < 2 or not all(parts):
            raise CommandError(f"--set {item!r}: expected SECTION.KEY=VALUE, e.g. --set train.lr=1e-3")
        if sections is not None and parts[0] not in sections:
            raise CommandError(f"--set {item!r}: no section {parts[0]!r} (this command's: {', '.join(sections)})")
        d = out
        for k in parts[:-1]:
            d = d.setdefault(k, {})
            if not isinstance(d, dict):
                raise CommandError(f"--set {item!r}: {k} is a value, not a section")
        d[parts[-1]] = parse_value(value.strip())
    return out


def _copy(d):
    return {k: _copy(v) for k, v in d.items()} if isinstance(d, dict) else d


def merge(*layers: dict) -> dict:
    """Recipes merged key by key, later ones winning (nested sections merged too)."""
    out: dict = {}
    for layer in layers:
        for k, v in (layer or {}).items():
            out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else _copy(v)
    return out


def build(cls: type, values: dict, section: str, base: object | None = None):
    """Dataclass ``cls`` from ``base`` (an instance; default: the field defaults) with ``values`` (a recipe
    section) set. Unknown keys, values of the wrong type and values its checks refuse raise a one-line
    CommandError naming ``section`` and the key."""
    values = values or {}
    if not isinstance(values, dict):
        raise CommandError(f"[{section}] must be a section (a table of settings), got {values!r}")
    names = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise CommandError(f"[{section}]: no setting {', '.join(unknown)} (settings: {', '.join(sorted(names))})")
    hints = _hints(cls)
    kw = {}
    for k, v in values.items():
        tp = hints[k]
        sub = _unwrap(tp)[0]
        if dataclasses.is_dataclass(sub) and isinstance(v, dict):
            kw[k] = build(sub, v, f"{section}.{k}", getattr(base, k, None) if base is not None else None)
        else:
            kw[k] = _convert(v, tp, f"{section}.{k}")
    try:
        return dataclasses.replace(base, **kw) if base is not None else cls(**kw)
    except (TypeError, ValueError) as e:
        raise CommandError(setting_message(str(e), names, section)) from None


def setting_message(msg: str, names, section: str) -> str:
    """A config's check message for the user: one that starts with a field name names its option and its recipe
    key (``max_steps must be >= 1`` -> ``--max-steps must be >= 1 (recipe: train.max_steps)``)."""
    first = msg.split(" ", 1)[0]
    if first in names:
        return f"{option_name(first)}{msg[len(first) :]} (recipe: {section}.{first})"
    return f"[{section}]: {msg}"


def to_recipe(obj) -> dict:
    """A dataclass as a recipe section: ``dataclasses.asdict`` with tuples as lists."""
    return _plain_value(dataclasses.asdict(obj))


def _plain_value(v):
    if isinstance(v, dict):
        return {k: _plain_value(x) for k, x in v.items()}
    if isinstance(v, (tuple, list)):
        return [_plain_value(x) for x in v]
    return v


def dump_recipe(recipe: dict, header: str = "") -> str:
    """``recipe`` (sections of settings, sections nested at most as deep as needed) as TOML text; None is written
    as ``"none"``. :func:`read_recipe` reads it back to the same values."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()] if header else []

    def emit(table: dict, name: str) -> None:
        scalars = {k: v for k, v in table.items() if not isinstance(v, dict)}
        subs = {k: v for k, v in table.items() if isinstance(v, dict)}
        if name and (scalars or not subs):
            if lines:
                lines.append("")
            lines.append(f"[{name}]")
        for k, v in scalars.items():
            lines.append(f"{_key(k)} = {_toml(v)}")
        for k, v in subs.items():
            emit(v, f"{name}.{_key(k)}" if name else _key(k))

    emit(recipe, "")
    return "\n".join(lines) + "\n"


def _key(k: str) -> str:
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml(k)


def _toml(v) -> str:
    if v is None:
        return f'"{NONE}"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isinf(v) or math.isnan(v):
            return {True: "inf", False: "-inf"}[v > 0] if math.isinf(v) else "nan"
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_toml(x)}" for k, x in v.items()) + " }"
    raise TypeError(f"cannot write {type(v).__name__} {v!r} to a recipe")


def first_difference(saved: dict, now: dict, prefix: str = "") -> tuple[str, object, object] | None:
    """The first setting where two resolved recipes differ: ``(dotted key, saved value, value now)`` (a setting
    missing on one side counts as a difference, its value ``"<absent>"``); None when they are equal."""
    for k in sorted(set(saved) | set(now), key=str):
        a, b = saved.get(k, "<absent>"), now.get(k, "<absent>")
        if isinstance(a, dict) and isinstance(b, dict):
            d = first_difference(a, b, f"{prefix}{k}.")
            if d:
                return d
        elif _plain_value(a) != _plain_value(b):
            return f"{prefix}{k}", a, b
    return None


def _show(v) -> str:
    return NONE if v is None else str(v)
