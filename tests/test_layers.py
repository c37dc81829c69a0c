"""The import layering of the ermrl package, read from its source with ``ast`` (nothing is imported).

Every ``import``/``from ... import`` of an ermrl module is collected, relative imports resolved,
with where it runs:

- ``module``: at import time (module body, class bodies, ``try``/``if`` blocks at top level);
- ``function``: inside a function (deferred until the function is called);
- ``type-checking``: under ``if TYPE_CHECKING:`` (never runs; a dependency for the type checker).

Four rules:

1. **No import cycle between units, whatever the kind of import.** A unit is a subpackage
   (``ermrl.search``) or a top-level module (``ermrl.config``, ``ermrl.__main__``). The graph of
   every import between units (``module``, ``function`` and ``type-checking`` alike) must be
   acyclic: arrows point one way. A function-level import still makes the importer depend on
   the imported unit, so one that goes back down the graph closes a circle as surely as a
   module-level one; at module level a cycle also means which unit finishes importing first
   depends on which one a caller happened to import first. A back arrow that cannot be avoided
   goes in :data:`ALLOWED_BACK_IMPORTS` with its reason (none today).
2. **No import cycle between the modules of one unit**, whatever the kind of import
   (``ermrl.search._evolve`` uses ``ermrl.search._generalization``, never the other way). Only
   imports of the unit's own ``__init__`` by its modules are left out: the ``__init__`` imports
   every module to re-export it, and a module reads the unit's registry through it
   (``ermrl.learners._base`` reads ``LEARNERS`` from ``ermrl.learners``).
3. **Layering.** :data:`LAYERS` orders the units, lowest first. A module may import from its own
   layer or a lower one, never a higher one, whatever the kind of import (a function-level or
   ``TYPE_CHECKING`` import still ties the lower layer to the higher one). The order is the one the
   package's concepts give: what every layer needs of the configuration (``ermrl._config_base``:
   the configuration error, limits, ranges, tasks and agent kinds; and ``ermrl._io``, atomic file
   writes), then environments, encoders (each one module that owns its settings, search space,
   flags and agents, and the registry), the run's configuration (``ermrl.config``: above the
   encoders, so that it reads a stored study's encoder settings as the registered encoder's
   classes and lists the registered encoders' agents; it re-exports what it builds on), the
   inner-loop learners (each algorithm, its agent's files and
   the reading of the expert folders that imitation learners query; the test-phase agent table,
   which lists the learners' agents and the encoders'), the agents (the training
   loop and the settings it resolves), the experts (trained and evaluated by the agents' loop),
   the population backend (which
   trains many agents at once with the agents' seeds and files), storage, the outer-loop search,
   analysis (which only reads results: studies and run folders), the test phase
   (``ermrl.test_phase``, which writes run folders and summarizes them with analysis), the
   runner (experiment files and the Python API, which drive all of them, and the commands'
   options, an experiment file's schema), and the CLI on top (it parses argv with those options,
   calls the runner and prints). Storage sits above agents and below search, where the concepts
   put it: measured, it imports no other ermrl unit and only units above it (search, analysis,
   the test phase, the runner and the CLI) import it, so it needs no other place to avoid
   violations.
4. The same cycle check at module level only (rule 1 implies it; its message says which unit
   would import first).

Violations that exist today are listed in :data:`KNOWN_VIOLATIONS`, each with why it is there,
so that the test fails on any new one; when one disappears the test fails until it is removed
from the set. Dynamic imports (``importlib.import_module`` with a computed name) are not seen.
"""

from __future__ import annotations

import ast
import functools
import graphlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import pytest

PACKAGE = "ermrl"
PACKAGE_DIR = Path(__file__).resolve().parents[1] / PACKAGE

# Lowest first. A unit may import from its own row and the rows above it in this table.
# The package's own __init__ (only its version) is the bottom: every module may import it.
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "ermrl",
        "ermrl._blas",
        "ermrl._code",
        "ermrl._config_base",
        "ermrl._interrupt",
        "ermrl._io",
        "ermrl._progress",
        "ermrl._schema",
        "ermrl._text",
    ),
    ("ermrl.envs",),
    ("ermrl.encoders",),
    ("ermrl.config",),
    ("ermrl.learners",),
    ("ermrl.agents",),
    ("ermrl.experts",),
    ("ermrl.population",),
    ("ermrl.storage",),
    ("ermrl.search",),
    ("ermrl.analysis",),
    # ermrl.experiments: the test phase's old name, a deprecated alias of ermrl.test_phase.
    ("ermrl.test_phase", "ermrl.experiments"),
    # The runner defines the commands' options (ermrl.runner._parsers: an experiment file's
    # schema); the CLI parses argv with them, calls the runner and prints.
    ("ermrl.runner",),
    ("ermrl.cli", "ermrl.__main__"),
)
ALL_KINDS = frozenset({"module", "function", "type-checking"})
LAYER_OF: dict[str, int] = {unit: i for i, row in enumerate(LAYERS) for unit in row}

# (importer module, imported module) pairs that break the layering today. Each one is a debt:
# fix it by moving the shared code down a layer, then remove its entry here (the test says so).
KNOWN_VIOLATIONS: frozenset[tuple[str, str]] = frozenset()

# (importer unit, imported unit) -> why: imports left out of the cycle check between units
# (rule 1), so that a circle they close is accepted. Empty: every arrow points one way.
ALLOWED_BACK_IMPORTS: dict[tuple[str, str], str] = {}


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


@functools.cache
def reexports(package: str) -> dict[str, str]:
    """``{name: defining module}`` of the names a package's ``__init__`` imports from its own
    modules (empty for a module that is not a package)."""
    path = module_path(package)
    if path.name != "__init__.py":
        return {}
    found = {}
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(package + "."):
            found.update({alias.asname or alias.name: node.module for alias in node.names})
    return found


def _imports_of(name: str, path: Path, modules: dict[str, Path]) -> list[Import]:
    """All imports of ermrl modules in one module, resolved to module names."""
    is_package = path.name == "__init__.py"
    found: list[Import] = []

    def resolve(base: str, names: list[str]) -> set[str]:
        # ``from base import x``: x is a submodule when one exists; a name a package re-exports
        # from one of its modules is that module (``from ermrl.runner import plan_steps`` in a
        # runner module depends on the module that defines it); else a name defined in base.
        targets = set()
        for n in names:
            target = f"{base}.{n}"
            targets.add(target if target in modules else reexports(base).get(n, base))
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


def import_cycle(
    imports: list[Import],
    node: Callable[[str], str] = unit_of,
    kinds: frozenset[str] = ALL_KINDS,
    skip: Callable[[Import], bool] = lambda imp: False,
) -> str | None:
    """A description of one import cycle, or ``None``.

    Args:
        imports: The imports found.
        node: The graph's node of a module (its unit by default; the module itself for cycles
            between the modules of one unit).
        kinds: The kinds of import that are arrows.
        skip: Imports that are no arrow.

    Returns:
        The cycle, importer first (``a -> b -> a``), then the import sites of each arrow.
    """
    arrows = [
        imp
        for imp in imports
        if imp.kind in kinds and node(imp.importer) != node(imp.imported) and not skip(imp)
    ]
    graph: dict[str, set[str]] = {}
    for imp in arrows:
        graph.setdefault(node(imp.importer), set()).add(node(imp.imported))
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as err:
        # Each node of the reported cycle is imported by the next one.
        cycle = err.args[1]
        sites = [
            str(imp)
            for imported, importer in zip(cycle, cycle[1:])
            for imp in arrows
            if node(imp.importer) == importer and node(imp.imported) == imported
        ]
        return " -> ".join(reversed(cycle)) + ":\n  " + "\n  ".join(sites)
    return None


def module_level_cycle(imports: list[Import]) -> str | None:
    """A description of one cycle of module-level imports between units, or ``None``."""
    return import_cycle(imports, kinds=frozenset({"module"}))


def _allowed_back_import(imp: Import) -> bool:
    return (unit_of(imp.importer), unit_of(imp.imported)) in ALLOWED_BACK_IMPORTS


def _imports_own_init(imp: Import) -> bool:
    return imp.imported == unit_of(imp.importer) != imp.importer


def test_no_module_level_cycle_between_units(imports: list[Import]) -> None:
    cycle = module_level_cycle(imports)
    assert cycle is None, f"module-level import cycle between units {cycle}"


def test_no_cycle_between_units(imports: list[Import]) -> None:
    cycle = import_cycle(imports, skip=_allowed_back_import)
    assert cycle is None, (
        f"import cycle between units (function-level imports count too) {cycle}\n"
        "move the shared code down, or list an unavoidable arrow in ALLOWED_BACK_IMPORTS"
    )


def test_allowed_back_imports_still_exist(imports: list[Import]) -> None:
    found = {(unit_of(imp.importer), unit_of(imp.imported)) for imp in imports}
    gone = sorted(set(ALLOWED_BACK_IMPORTS) - found)
    assert not gone, f"gone, remove from ALLOWED_BACK_IMPORTS in tests/test_layers.py: {gone}"


@pytest.mark.parametrize("unit", sorted({unit_of(name) for name in package_modules()}))
def test_no_cycle_between_modules_of_a_unit(imports: list[Import], unit: str) -> None:
    inside = [imp for imp in imports if unit_of(imp.importer) == unit_of(imp.imported) == unit]
    cycle = import_cycle(inside, node=lambda module: module, skip=_imports_own_init)
    assert cycle is None, f"import cycle between modules of {unit} {cycle}"


def test_cycle_is_detected() -> None:
    # Guards the check itself: a function-level import closes no module-level cycle, but it
    # does close a cycle between units; an allowed back import closes none.
    down = Import("ermrl.search._evolve", "ermrl.storage._open", "module", 1)
    up = Import("ermrl.storage._open", "ermrl.search", "function", 1)
    assert module_level_cycle([down, up]) is None
    for found in (import_cycle([down, up]), module_level_cycle([down, replace(up, kind="module")])):
        assert found is not None and "ermrl.search" in found and "ermrl.storage" in found
        assert "storage/_open.py" in found  # the import sites are printed
    assert import_cycle([down, up], skip=lambda imp: imp is up) is None


def test_cycle_between_modules_is_detected() -> None:
    evolve = Import("ermrl.search._evolve", "ermrl.search._generalization", "function", 1)
    back = Import("ermrl.search._generalization", "ermrl.search._evolve", "type-checking", 1)
    registry = Import("ermrl.search._evolve", "ermrl.search", "function", 1)
    init = Import("ermrl.search", "ermrl.search._evolve", "module", 1)

    def cycle(found: list[Import]) -> str | None:
        return import_cycle(found, node=lambda module: module, skip=_imports_own_init)

    assert cycle([evolve, registry, init]) is None
    found = cycle([evolve, back, registry, init])
    assert found is not None and "ermrl.search._generalization" in found


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
        ("ermrl.analysis._results", "type-checking"),  # re-exported by ermrl.analysis
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


def test_the_configuration_imports_no_training_library() -> None:
    """Reading a configuration (every command's parser, ``ermrl run --dry-run``) must not pay
    for reservoirpy, scipy.stats, stable-baselines3 or torch: they took 10 of the dry run's 18
    seconds when ``ermrl.encoders`` imported them with itself."""
    import subprocess
    import sys

    code = (
        "import sys, ermrl.config, ermrl.encoders\n"
        "heavy = ('reservoirpy', 'stable_baselines3', 'torch', 'scipy.stats')\n"
        "print(' '.join(m for m in heavy if m in sys.modules))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "", done.stdout
    # The lazily imported names are still there for whoever asks.
    code = (
        "from ermrl.encoders import ActionEncoder, ReservoirVecEnv; print(ReservoirVecEnv.__name__)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "ReservoirVecEnv"
