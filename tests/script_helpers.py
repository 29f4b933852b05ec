"""Load a file of ``scripts/`` (or any Python file) as a module, for tests of code that is not in the package."""
from __future__ import annotations

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
