"""The package's import graph, read from the source (nothing is imported): no import cycle, no
cross-module import of a ``_private`` name (a helper shared by modules has a public name, in
``__all__`` or not), no import from a higher layer of the package (:data:`LAYERS`), and no
module over 800 lines (issue 33).

Imports inside functions count (they still tie the modules together); imports under
``if TYPE_CHECKING:`` do not (they never run). The cycles not yet broken are listed below; the
list may only shrink: a listed cycle that is gone fails the test until it is taken off.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "hgpdm_torch"
#: cycles not yet broken, each as its sorted modules
KNOWN_CYCLES: set[tuple[str, ...]] = set()

#: the package's layers, lowest first: a module may import its own layer and those below it
#: (docs, architecture); a new top-level module or package needs a place here
LAYERS = (
    {"validation", "settings", "native", "tiling", "progress", "linalg", "results", "parallel"}
    | {"_lazy"},
    {"gaussian", "kernels", "fitting", "calibration", "crossval", "quadrature"},
    {"leaves", "expectations", "moments", "gp_shared", "gp", "observations", "intention_belief"},
    {"models"},
    {"inference"},
    {"model_selection", "baselines", "datasets"},
    {"decision", "robots"},
    {"experiments"},
    {"cli", ""},  # "": the package's __init__
)
#: imports from a higher layer not yet removed (importer, imported); the list may only shrink
KNOWN_UPWARD: set[tuple[str, str]] = set()


def _modules() -> dict[str, tuple[Path, list[str]]]:
    """Module name -> (file, package parts its relative imports start from)."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = ["hgpdm_torch", *path.relative_to(PACKAGE).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
            out[".".join(parts)] = (path, parts)
        else:
            out[".".join(parts)] = (path, parts[:-1])
    return out


class _Imports(ast.NodeVisitor):
    """``(target module, imported names)`` of every import that runs."""

    def __init__(self, package: list[str]) -> None:
        self.package, self.found = package, []

    def visit_If(self, node: ast.If) -> None:
        test = node.test
        name = test.id if isinstance(test, ast.Name) else getattr(test, "attr", None)
        if name == "TYPE_CHECKING":
            for child in node.orelse:
                self.visit(child)
            return
        self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        self.found += [(alias.name, []) for alias in node.names]

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            base = self.package[: len(self.package) - node.level + 1]
            target = ".".join([*base, *([node.module] if node.module else [])])
        else:
            target = node.module or ""
        self.found.append((target, [alias.name for alias in node.names]))


def import_graph() -> tuple[dict[str, set[str]], list[tuple[str, str, str]]]:
    """Edges between the package's modules, and the ``(importer, module, _name)`` imports."""
    modules = _modules()
    edges: dict[str, set[str]] = {m: set() for m in modules}
    private = []
    for name, (path, package) in modules.items():
        visitor = _Imports(package)
        visitor.visit(ast.parse(path.read_text()))
        for target, names in visitor.found:
            if not target.startswith("hgpdm_torch"):
                continue
            for imported in names or [None]:
                sub = f"{target}.{imported}" if imported else target
                dest = sub if sub in modules else target
                if dest in modules and dest != name:
                    edges[name].add(dest)
                if imported and imported.startswith("_") and not imported.startswith("__"):
                    if sub not in modules and target != name:
                        private.append((name, target, imported))
    return edges, private


def cycles(edges: dict[str, set[str]]) -> set[tuple[str, ...]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = set()

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.add(tuple(sorted(component)))

    for v in edges:
        if v not in index:
            visit(v)
    return found


def test_no_new_import_cycle():
    found = cycles(import_graph()[0])
    assert found - KNOWN_CYCLES == set(), f"new import cycles: {found - KNOWN_CYCLES}"
    assert KNOWN_CYCLES - found == set(), f"cycles gone, take them off: {KNOWN_CYCLES - found}"


def test_no_private_import_across_modules():
    private = import_graph()[1]
    assert private == [], (
        f"cross-module imports of _private names {private}: give the helper a public name "
        "(it need not be in __all__) or move it where it is used"
    )


def layer(module: str) -> int:
    """The index in :data:`LAYERS` of ``module``'s top-level module or package."""
    top = module.split(".")[1] if "." in module else ""
    found = [i for i, names in enumerate(LAYERS) if top in names]
    assert found, f"{module}: {top!r} has no layer; add it to LAYERS"
    return found[0]


def test_no_import_from_a_higher_layer():
    edges = import_graph()[0]
    upward = {(a, b) for a, targets in edges.items() for b in targets if layer(b) > layer(a)}
    assert upward - KNOWN_UPWARD == set(), f"imports from a higher layer: {upward - KNOWN_UPWARD}"
    assert KNOWN_UPWARD - upward == set(), f"gone, take them off: {KNOWN_UPWARD - upward}"


#: the most lines a module may have: beyond it a module holds more than one concept (issue 33)
MAX_LINES = 800


def test_no_module_over_800_lines():
    sizes = {path.relative_to(PACKAGE).as_posix(): len(path.read_text().splitlines())
             for path, _ in _modules().values()}  # fmt: skip
    long = {name: n for name, n in sizes.items() if n > MAX_LINES}
    assert long == {}, f"modules over {MAX_LINES} lines, split them by concern: {long}"


def test_the_walk_finds_a_cycle_and_skips_type_checking_imports():
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(edges) == {("a", "b", "c")}
    assert layer("hgpdm_torch.linalg") < layer("hgpdm_torch.models.gpdm") < layer("hgpdm_torch")
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .x import y\n"
                     "def f():\n    from .z import _w\n")  # fmt: skip
    visitor = _Imports(["hgpdm_torch", "pkg"])
    visitor.visit(tree)
    assert visitor.found == [("typing", ["TYPE_CHECKING"]), ("hgpdm_torch.pkg.z", ["_w"])]
