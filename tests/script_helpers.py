"""Load a Python file as a module (tests of code that is not in the package, e.g. fixture makers), and the
analyses of ``tsnav analyze`` as fresh modules."""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from types import ModuleType

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(path: str | Path, name: str | None = None) -> ModuleType:
    """The module of ``path`` (a bare name means ``scripts/<name>.py``), executed fresh on each call."""
    path = Path(path)
    if path.suffix != ".py":
        path = SCRIPTS / f"{path}.py"
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_analysis(name: str) -> ModuleType:
    """The module of ``tsnav analyze`` analysis ``name`` (``tsnav.analyze.<name>``), executed fresh on each call."""
    return importlib.reload(importlib.import_module(f"tsnav.analyze.{name}"))
