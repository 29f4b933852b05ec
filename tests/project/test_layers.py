"""The layer rule of docs/ARCHITECTURE.md: a package imports only packages of lower layers (and itself), and no
modules import each other in a circle. Every import counts, also those inside functions."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "tsnav"

#: Lowest first; the same list is drawn in docs/ARCHITECTURE.md ("Layers"). Packages of one layer do not
#: import each other.
LAYERS: list[set[str]] = [
    {"constants", "errors", "atomic", "distributed", "schedule", "checkpoint_layout", "protocol"},
    {"metrics", "checkpoint", "scene_pool", "settings"},
    {"render"},
    {"data"},
    {"world"},
    {"sim"},
    {"tsrm"},
    {"detect", "pretrain"},
    {"agent"},
    {"rl"},
    {"eval", "thor"},
    {"report"},
    {"pipeline"},
    {"analyze"},
    {"cli"},
    {"__main__", "cli_reference"},
]
RANK = {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def tsnav_imports(path: Path, root: Path) -> list[tuple[str, int]]:
    """``(imported tsnav module, line)`` of every import statement in ``path`` (module level or not)."""
    mod = module_name(path, root)
    package = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                stem = ".".join(base + ([node.module] if node.module else []))
                # ``from . import x`` may name a module x of the package
                names = [f"{stem}.{a.name}" if not node.module else stem for a in node.names]
            else:
                names = [node.module]
        else:
            continue
        out += [(n, node.lineno) for n in names if n == "tsnav" or n.startswith("tsnav.")]
    return out


def package_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def import_graph(root: Path) -> dict[str, list[tuple[str, int]]]:
    modules = {module_name(p, root): p for p in root.rglob("*.py")}
    graph = {}
    for mod, p in modules.items():
        edges = []
        for target, line in tsnav_imports(p, root):
            while target not in modules and "." in target:  # ``from pkg.mod import name``: name is no module
                target = target.rsplit(".", 1)[0]
            if target != mod:
                edges.append((target, line))
        graph[mod] = edges
    return graph


def layer_violations(root: Path) -> list[str]:
    bad = []
    for mod, edges in import_graph(root).items():
        a = package_of(mod)
        for target, line in edges:
            b = package_of(target)
            if a == b or not b:
                continue
            if a not in RANK or b not in RANK:
                bad.append(f"{mod}:{line} imports {target}: package {a if a not in RANK else b!r} has no layer")
            elif RANK[b] >= RANK[a]:
                bad.append(f"{mod}:{line} imports {target}: layer of {b!r} is not below that of {a!r}")
    return bad


def import_cycles(root: Path) -> list[list[str]]:
    """Strongly connected sets of more than one module (Tarjan)."""
    graph = {m: sorted({t for t, _ in e if t in import_graph_cache(root)}) for m, e in import_graph_cache(root).items()}
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


_CACHE: dict[Path, dict] = {}


def import_graph_cache(root: Path) -> dict:
    if root not in _CACHE:
        _CACHE[root] = import_graph(root)
    return _CACHE[root]


def test_every_package_has_a_layer():
    packages = {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    modules = {p.stem for p in SRC.glob("*.py") if p.stem != "__init__"}
    assert packages | modules <= set(RANK), f"no layer for {sorted((packages | modules) - set(RANK))}"


def test_lower_layers_never_import_higher_ones():
    bad = layer_violations(SRC)
    assert not bad, "layer rule broken (docs/ARCHITECTURE.md):\n" + "\n".join(bad)


def test_no_import_cycles():
    cycles = import_cycles(SRC)
    assert not cycles, f"modules importing each other in a circle: {cycles}"


def test_the_rule_catches_an_upward_import(tmp_path):
    """The check itself: a data module importing the eval package, and two modules importing each other."""
    root = tmp_path / "tsnav"
    for pkg in ("data", "eval"):
        (root / pkg).mkdir(parents=True)
        (root / pkg / "__init__.py").write_text("")
    (root / "__init__.py").write_text("")
    (root / "data" / "reader.py").write_text("def f():\n    from ..eval.metrics import METRICS\n")
    (root / "eval" / "metrics.py").write_text("from ..data import reader\nfrom . import runner\nMETRICS = ()\n")
    (root / "eval" / "runner.py").write_text("from .metrics import METRICS\n")
    bad = layer_violations(root)
    assert len(bad) == 1 and bad[0].startswith("tsnav.data.reader:2 imports tsnav.eval.metrics")
    assert import_cycles(root) == [["tsnav.eval.metrics", "tsnav.eval.runner"]]


@pytest.mark.parametrize("pkg", sorted(RANK))
def test_layers_are_drawn_in_the_architecture_doc(pkg):
    doc = (SRC.parents[1] / "docs" / "ARCHITECTURE.md").read_text()
    assert f"`{pkg}`" in doc.split("## Layers", 1)[-1].split("\n## ", 1)[0]
