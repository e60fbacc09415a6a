"""The package's import graph, built from the modules' own import statements (module level and in functions).

Checks: no cycle; no arrow from a lower layer to a higher one (:data:`LAYERS`, bottom first); no
module imports another module's private (underscore) names, except a package's private modules
imported from inside that package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "implicit_cloth"

#: Bottom first. A module may import from its own layer (the graph must stay acyclic) or any lower one.
#: A prefix ending in "*" stands for a package and everything in it.
LAYERS: list[tuple[str, ...]] = [
    ("errors", "materials", "kernels*", "interrupt", "rowwise"),
    ("config*", "report", "backend", "forces"),
    ("files", "geometry", "obstacles", "objfile", "cloth", "pin_paths"),
    ("scene",),
    ("assembly", "solvers*", "effects*"),
    ("model", "constraints"),
    ("integrators*", "collision*", "contact*", "selfcontact*", "diagnostics", "adaptive", "strain_limit"),
    ("simulator",),
    ("",),                                   # the package itself: the public API's facade
    ("results", "export*", "renderer", "render", "batch*", "compare"),
    ("cli", "__main__"),
]


def _modules() -> dict[str, Path]:
    out = {}
    for f in sorted(PKG.rglob("*.py")):
        parts = list(f.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> list[tuple[str, str | None, int]]:
    """``(target module, imported name or None, line)`` of every import of the package in ``name``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names if a.name.startswith("implicit_cloth")]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("implicit_cloth"):
                continue
            for a in node.names:
                sub = f"{target}.{a.name}"
                out.append((sub, None, node.lineno) if sub in MODULES else (target, a.name, node.lineno))
    return out


EDGES = {m: sorted({t for t, _, _ in _imports(m, p) if t != m}) for m, p in MODULES.items()}


def _layer(module: str) -> int:
    rel = module[len("implicit_cloth."):] if module != "implicit_cloth" else ""
    for level, names in enumerate(LAYERS):
        for n in names:
            if rel == n or (n.endswith("*") and (rel == n[:-1] or rel.startswith(n[:-1] + "."))):
                return level
    raise AssertionError(f"{module}: in no layer of tests/test_architecture.py LAYERS; add it where it belongs")


def test_the_graph_is_built_from_real_imports():
    # known arrows, so that a broken parser cannot pass the other tests by finding nothing
    assert "implicit_cloth.assembly" in EDGES["implicit_cloth.model"]
    assert "implicit_cloth.config.validate" in EDGES["implicit_cloth.scene"]
    assert "implicit_cloth.batch" in EDGES["implicit_cloth.compare"]
    assert "implicit_cloth.kernels.pcg" in EDGES["implicit_cloth.solvers.multigrid"]
    assert sum(len(v) for v in EDGES.values()) > 100


def test_every_module_has_a_layer():
    for m in MODULES:
        _layer(m)


def test_no_import_cycle():
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in EDGES.get(m, []):
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if t in MODULES and t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in MODULES:
        if m not in state:
            visit(m)


def test_no_upward_arrow():
    up = [f"{m} (layer {_layer(m)}) -> {t} (layer {_layer(t)})"
          for m, targets in EDGES.items() for t in targets if t in MODULES and _layer(t) > _layer(m)]
    assert up == []


def test_no_module_imports_another_modules_private_names():
    bad = []
    for m, p in MODULES.items():
        for target, name, line in _imports(m, p):
            private = [part for part in target.split(".") if part.startswith("_") and not part.startswith("__")]
            if private:   # a private module: only from inside the package that holds it
                owner = target[: target.index("." + private[0])]
                if not (m == owner or m.startswith(owner + ".")):
                    bad.append(f"{p.relative_to(PKG.parent)}:{line}: {target}")
            if name is not None and name.startswith("_") and not name.startswith("__") and target != m:
                bad.append(f"{p.relative_to(PKG.parent)}:{line}: {target}.{name}")
    assert bad == []
