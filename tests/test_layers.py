"""The import layering of the ermrl package, read from its source with ``ast`` (nothing is imported).

Every ``import``/``from ... import`` of an ermrl module is collected, relative imports resolved,
with where it runs:

- ``module``: at import time (module body, class bodies, ``try``/``if`` blocks at top level);
- ``function``: inside a function (deferred until the function is called);
- ``type-checking``: under ``if TYPE_CHECKING:`` (never runs; a dependency for the type checker).

Two rules:

1. **No import cycle between units at module level.** A unit is a subpackage (``ermrl.search``)
   or a top-level module (``ermrl.config``, ``ermrl.__main__``). The graph of ``module`` imports
   between units must be acyclic: a cycle means which unit finishes importing first depends on
   which one a caller happened to import first.
2. **Layering.** :data:`LAYERS` orders the units, lowest first. A module may import from its own
   layer or a lower one, never a higher one, whatever the kind of import (a function-level or
   ``TYPE_CHECKING`` import still ties the lower layer to the higher one). The order is the one the
   package's concepts give: configuration (and ``ermrl._io``, atomic file writes), then
   environments, encoders, the inner-loop learners and agents (with the experts that imitation
   learners query, trained by the agents' loop), the population backend (which
   trains many agents at once with the agents' seeds and files), storage, the outer-loop search,
   analysis (which only reads results: studies and run folders), experiments (the test phase,
   which writes run folders and summarizes them with analysis), and the CLI on top. Storage sits above agents and below search, where the concepts put it: measured, it
   imports no other ermrl unit and only search, analysis and the CLI import it, so it needs no
   other place to avoid violations.

Violations that exist today are listed in :data:`KNOWN_VIOLATIONS`, each with why it is there,
so that the test fails on any new one; when one disappears the test fails until it is removed
from the set. Dynamic imports (``importlib.import_module`` with a computed name) are not seen.
"""

from __future__ import annotations

import ast
import graphlib
from dataclasses import dataclass
from pathlib import Path

import pytest

PACKAGE = "ermrl"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE

# Lowest first. A unit may import from its own row and the rows above it in this table.
# The package's own __init__ (only its version) is the bottom: every module may import it.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("ermrl", "ermrl._interrupt", "ermrl._io", "ermrl._progress", "ermrl._text"),
    ("ermrl.config",),
    ("ermrl.envs",),
    ("ermrl.encoders",),
    ("ermrl.learners", "ermrl.agents", "ermrl.experts"),
    ("ermrl.population",),
    ("ermrl.storage",),
    ("ermrl.search",),
    ("ermrl.analysis",),
    ("ermrl.experiments",),
    ("ermrl.cli", "ermrl.__main__"),
)
LAYER_OF: dict[str, int] = {unit: i for i, row in enumerate(LAYERS) for unit in row}

# (importer module, imported module) pairs that break the layering today. Each one is a debt:
# fix it by moving the shared code down a layer, then remove its entry here (the test says so).
KNOWN_VIOLATIONS: frozenset[tuple[str, str]] = frozenset()


@dataclass(frozen=True)
class Import:
    """One import of an ermrl module found in the source."""

    importer: str  # module that imports
    imported: str  # resolved ermrl module
    kind: str  # "module", "function" or "type-checking"
    line: int

    def __str__(self) -> str:
        path = module_path(self.importer).relative_to(PACKAGE_DIR.parent)
        return f"{self.importer} -> {self.imported} ({self.kind} level, {path}:{self.line})"


def module_path(name: str) -> Path:
    """The source file of module ``name``."""
    parts = name.split(".")[1:]
    folder = PACKAGE_DIR.joinpath(*parts)
    return folder / "__init__.py" if folder.is_dir() else folder.with_suffix(".py")


def package_modules() -> dict[str, Path]:
    """``{module name: source file}`` for every module of the package."""
    modules = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        modules[".".join(parts)] = path
    return modules


def unit_of(module: str) -> str:
    """The layering unit of a module: ``ermrl.search._evolve`` -> ``ermrl.search``."""
    return ".".join(module.split(".")[:2])


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    """All imports of ermrl modules in one module, resolved to module names."""
    is_package = path.name == "__init__.py"
    found: list[Import] = []

    def resolve(base: str, names: list[str]) -> set[str]:
        # ``from base import x``: x is a submodule when one exists, else a name defined in base.
        targets = {f"{base}.{n}" for n in names if f"{base}.{n}" in modules}
        if len(targets) < len(names):
            targets.add(base)
        return targets

    def visit(node: ast.AST, kind: str) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            kind = "function" if kind == "module" else kind
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                visit(child, "type-checking")
            for child in node.orelse:
                visit(child, kind)
            return
        targets: set[str] = set()
        if isinstance(node, ast.Import):
            targets = {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = name.split(".")
                drop = node.level - 1 if is_package else node.level
                base = ".".join(parts[: len(parts) - drop] if drop else parts)
                if node.module:
                    base = f"{base}.{node.module}"
            else:
                base = node.module or ""
            if base == PACKAGE or base.startswith(PACKAGE + "."):
                targets = resolve(base, [alias.name for alias in node.names])
        for target in sorted(targets):
            if target == PACKAGE or target.startswith(PACKAGE + "."):
                found.append(Import(name, target, kind, getattr(node, "lineno", 0)))
        for child in ast.iter_child_nodes(node):
            visit(child, kind)

    visit(ast.parse(path.read_text(), filename=str(path)), "module")
    return found


@pytest.fixture(scope="module")
def imports() -> list[Import]:
    modules = package_modules()
    return [imp for name, path in modules.items() for imp in _imports_of(name, path, modules)]


def layer_violations(imports: list[Import]) -> dict[tuple[str, str], list[Import]]:
    """``{(importer, imported): [imports]}`` for every import from a higher layer."""
    found: dict[tuple[str, str], list[Import]] = {}
    for imp in imports:
        if LAYER_OF[unit_of(imp.imported)] > LAYER_OF[unit_of(imp.importer)]:
            found.setdefault((imp.importer, imp.imported), []).append(imp)
    return found


def test_imports_are_found(imports: list[Import]) -> None:
    # Guards the parser: the CLI imports the search, relative imports resolve to real modules.
    assert any(
        imp.importer.startswith("ermrl.cli") and unit_of(imp.imported) == "ermrl.search"
        for imp in imports
    )
    modules = package_modules()
    unknown = sorted({imp.imported for imp in imports} - set(modules))
    assert not unknown, f"imports of ermrl modules that do not exist: {unknown}"


def test_every_unit_has_a_layer() -> None:
    units = {unit_of(name) for name in package_modules()}
    missing = sorted(units - set(LAYER_OF))
    assert not missing, f"give each new subpackage/module a row in LAYERS: {missing}"


def module_level_cycle(imports: list[Import]) -> str | None:
    """A description of one cycle of module-level imports between units, or ``None``."""
    graph: dict[str, set[str]] = {}
    for imp in imports:
        a, b = unit_of(imp.importer), unit_of(imp.imported)
        graph.setdefault(a, set())
        if imp.kind == "module" and a != b:
            graph[a].add(b)
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as err:
        # Each node of the reported cycle is imported by the next one.
        cycle = err.args[1]
        sites = [
            str(imp)
            for imported, importer in zip(cycle, cycle[1:])
            for imp in imports
            if imp.kind == "module"
            and unit_of(imp.importer) == importer
            and unit_of(imp.imported) == imported
        ]
        return " -> ".join(reversed(cycle)) + ":\n  " + "\n  ".join(sites)
    return None


def test_no_module_level_cycle_between_units(imports: list[Import]) -> None:
    cycle = module_level_cycle(imports)
    assert cycle is None, f"module-level import cycle between units {cycle}"


def test_cycle_is_detected() -> None:
    # Guards the check itself: a function-level import closes no cycle, a module-level one does.
    down = Import("ermrl.search._evolve", "ermrl.storage._open", "module", 1)
    up = Import("ermrl.storage._open", "ermrl.search", "function", 1)
    assert module_level_cycle([down, up]) is None
    cycle = module_level_cycle([down, Import(up.importer, up.imported, "module", 1)])
    assert cycle is not None and "ermrl.search" in cycle and "ermrl.storage" in cycle


def test_parser_resolves_imports(tmp_path: Path) -> None:
    source = tmp_path / "_fake.py"
    source.write_text(
        "from typing import TYPE_CHECKING\n"
        "import ermrl.config\n"
        "from . import _objective, helper\n"
        "from ..agents._train import train_agent\n"
        "if TYPE_CHECKING:\n"
        "    from ermrl.analysis import load_curves\n"
        "def f():\n"
        "    from ermrl.cli import main\n"
    )
    modules = dict.fromkeys(
        ["ermrl.config", "ermrl.search", "ermrl.search._objective", "ermrl.agents._train"],
        source,
    )
    found = {(i.imported, i.kind) for i in _imports_of("ermrl.search._fake", source, modules)}
    assert found == {
        ("ermrl.config", "module"),
        ("ermrl.search._objective", "module"),
        ("ermrl.search", "module"),  # ``helper`` is a name defined in ermrl.search
        ("ermrl.agents._train", "module"),
        ("ermrl.analysis", "type-checking"),
        ("ermrl.cli", "function"),
    }


def test_no_new_layer_violation(imports: list[Import]) -> None:
    new = {
        pair: sites
        for pair, sites in layer_violations(imports).items()
        if pair not in KNOWN_VIOLATIONS
    }
    lines = [str(imp) for sites in new.values() for imp in sites]
    assert not new, (
        "imports from a higher layer (see LAYERS in tests/test_layers.py):\n  " + "\n  ".join(lines)
    )


def test_known_violations_still_exist(imports: list[Import]) -> None:
    gone = sorted(KNOWN_VIOLATIONS - set(layer_violations(imports)))
    assert not gone, f"fixed, remove from KNOWN_VIOLATIONS in tests/test_layers.py: {gone}"


def test_search_never_imports_an_encoders_own_types() -> None:
    """The outer loop samples plain dicts and lets the encoder decode them (ermrl.encoders)."""
    own = {"ReservoirParams", "ReservoirSpace", "ReservoirVecEnv", "ReservoirBank"}
    found = []
    for path in sorted((PACKAGE_DIR / "search").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                found += [(path.name, a.name) for a in node.names if a.name in own]
    assert found == []
