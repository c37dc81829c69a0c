"""notebooks/*.ipynb: committed stripped, import only from ermrl.analysis, and execute.

CI executes every notebook with nbclient against the tiny study and test-phase folder of
tests/_analysis_data.py, pointing the notebooks' first cell at them through the environment
variables ERMRL_STUDY_NAME, ERMRL_STORAGE and ERMRL_RUNS. A failing cell fails the test.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import re
from pathlib import Path
from types import ModuleType

import pytest

from tests._analysis_data import TinyStudy, build_tiny_study

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
EXPECTED = [
    "01_evolution.ipynb",
    "02_test_results.ipynb",
    "03_reservoir_dynamics.ipynb",
    "04_generalization.ipynb",
]


def _nbformat() -> ModuleType:
    if importlib.util.find_spec("nbformat") is None or importlib.util.find_spec("nbclient") is None:
        message = "nbformat/nbclient missing: pip install -e '.[dev]'"
        if os.environ.get("ERMRL_REQUIRE_SERVICES") == "1":
            pytest.fail(message)
        pytest.skip(message)
    import nbformat

    return nbformat


def test_the_four_notebooks_exist() -> None:
    assert [p.name for p in NOTEBOOKS] == EXPECTED


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_is_stripped_and_imports_only_ermrl_analysis(path: Path) -> None:
    nbformat = _nbformat()
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert nb.cells[0].cell_type == "code"
    first = nb.cells[0].source
    for name in ("STUDY_NAME", "STORAGE", "RUNS"):
        assert name in first
    for cell in code:
        assert cell.outputs == [] and cell.execution_count is None, "commit notebooks stripped"
        for node in ast.walk(ast.parse(cell.source)):
            if isinstance(node, ast.Import):
                pytest.fail(
                    f"{path.name}: `import {node.names[0].name}`; import from ermrl.analysis"
                )
            if isinstance(node, ast.ImportFrom):
                assert node.module == "ermrl.analysis", f"{path.name} imports from {node.module}"


def test_the_notebooks_extra_brings_jupyter_lab_and_nbconvert() -> None:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11 and later
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    extra = pyproject["project"]["optional-dependencies"]["notebooks"]
    names = {re.split(r"[<>=\[ ]", spec, maxsplit=1)[0] for spec in extra}
    assert {"jupyter", "jupyterlab", "nbconvert", "ipykernel"} <= names


def _first_cell_defaults(path: Path) -> dict[str, str]:
    """The keyword arguments of the first cell's ``notebook_parameters(...)`` call."""
    nbformat = _nbformat()
    tree = ast.parse(nbformat.read(path, as_version=4).cells[0].source)
    (call,) = [
        n
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "notebook_parameters"
    ]
    return {k.arg: ast.literal_eval(k.value) for k in call.keywords if k.arg}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_the_first_cell_defaults_to_the_demo_study(path: Path) -> None:
    """Run after `make demo`, a notebook opens the demo's study and test phase, as
    experiments/demo.yaml names them (paths relative to notebooks/)."""
    from ermrl.cli._experiment import experiment_plan, load_experiment

    evolve, _, test, _ = experiment_plan(
        load_experiment(ROOT / "experiments" / "demo.yaml"), build_agents=False
    )

    def option(argv: list[str], name: str) -> str:
        return argv[argv.index(name) + 1]

    storage = option(evolve.argv, "--storage")
    assert storage.startswith("sqlite:///") and not storage.startswith("sqlite:////")
    assert _first_cell_defaults(path) == {
        "study_name": option(evolve.argv, "--study-name"),
        "storage": "sqlite:///../" + storage.removeprefix("sqlite:///"),
        "runs": "../" + option(test.argv, "--out"),
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> TinyStudy:
    return build_tiny_study(tmp_path_factory.getbasetemp())


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_executes(
    path: Path, tiny: TinyStudy, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    nbformat = _nbformat()
    from nbclient import NotebookClient

    monkeypatch.setenv("ERMRL_STUDY_NAME", tiny.study_name)
    monkeypatch.setenv("ERMRL_STORAGE", tiny.storage)
    monkeypatch.setenv("ERMRL_RUNS", str(tiny.runs))
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(
        nb,
        timeout=600,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path)}},
    )
    client.execute()  # raises CellExecutionError, with the failing cell, if any cell fails
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert images, "the notebook shows no figure"
    first = "".join(o.get("text", "") for o in nb.cells[0].outputs)
    assert tiny.study_name in first
