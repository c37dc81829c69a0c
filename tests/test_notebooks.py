"""notebooks/*.ipynb: committed stripped, with their imports limited, and execute.

The analysis notebooks (01-04) import only from ermrl.analysis. CI executes each with nbclient
against the tiny study and test-phase folder of tests/_analysis_data.py, pointing the notebooks'
first cell at them through the environment variables ERMRL_STUDY_NAME, ERMRL_STORAGE and
ERMRL_RUNS. The From-Python notebook (05) runs the demo's `quick` variant through the API at the
package root, and the objects notebook (06) evolves, trains, saves and reloads a model through
the object API; CI executes both as they are, in a temporary folder. A failing cell fails the test.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import re
import shutil
from pathlib import Path
from types import ModuleType

import pytest

from tests._analysis_data import TinyStudy, build_tiny_study

ROOT = Path(__file__).resolve().parents[1]
ALL_NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
EXPECTED = [
    "01_evolution.ipynb",
    "02_test_results.ipynb",
    "03_reservoir_dynamics.ipynb",
    "04_generalization.ipynb",
    "05_from_python.ipynb",
    "06_object_api.ipynb",
]
# The notebooks that analyse a study and its test phase (05 and 06 run the API instead).
NOTEBOOKS = [p for p in ALL_NOTEBOOKS if p.name not in EXPECTED[4:]]
FROM_PYTHON = ROOT / "notebooks" / "05_from_python.ipynb"
# What the From-Python notebook may import: the API at the package root, the analysis, pyplot.
FROM_PYTHON_IMPORTS = {"ermrl", "ermrl.analysis", "matplotlib.pyplot"}
OBJECTS = ROOT / "notebooks" / "06_object_api.ipynb"


def _nbformat() -> ModuleType:
    if importlib.util.find_spec("nbformat") is None or importlib.util.find_spec("nbclient") is None:
        message = "nbformat/nbclient missing: pip install -e '.[dev]'"
        if os.environ.get("ERMRL_REQUIRE_SERVICES") == "1":
            pytest.fail(message)
        pytest.skip(message)
    import nbformat

    return nbformat


def test_the_six_notebooks_exist() -> None:
    assert [p.name for p in ALL_NOTEBOOKS] == EXPECTED


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
    from ermrl.runner._experiment import experiment_plan, load_experiment

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


@pytest.mark.parametrize(
    ("path", "allowed"),
    [(FROM_PYTHON, FROM_PYTHON_IMPORTS), (OBJECTS, {"ermrl"})],
    ids=["05", "06"],
)
def test_the_api_notebooks_are_stripped_and_import_the_api(path: Path, allowed: set[str]) -> None:
    nbformat = _nbformat()
    nb = nbformat.read(path, as_version=4)
    imported = set()
    for cell in (c for c in nb.cells if c.cell_type == "code"):
        assert cell.outputs == [] and cell.execution_count is None, "commit notebooks stripped"
        for node in ast.walk(ast.parse(cell.source)):
            if isinstance(node, ast.Import):
                imported |= {alias.name for alias in node.names}
            if isinstance(node, ast.ImportFrom):
                imported.add(str(node.module))
    assert imported == allowed


def test_the_from_python_notebook_runs_the_demos_quick_variant() -> None:
    """Its first cell names the file and the variant; the variant exists and is small."""
    from ermrl.runner import Experiment

    nbformat = _nbformat()
    first = nbformat.read(FROM_PYTHON, as_version=4).cells[0].source
    assert '"../experiments/demo.yaml", "quick"' in first
    steps = Experiment.load(ROOT / "experiments" / "demo.yaml", variant="quick").plan()
    assert sum(s.env_steps for s in steps) <= 200_000


@pytest.mark.slow
def test_the_from_python_notebook_executes(tmp_path: Path) -> None:
    """In a copy of the layout it expects (notebooks/ beside experiments/), in about a minute."""
    nbformat = _nbformat()
    from nbclient import NotebookClient

    (tmp_path / "experiments").mkdir()
    shutil.copy(ROOT / "experiments" / "demo.yaml", tmp_path / "experiments" / "demo.yaml")
    (tmp_path / "notebooks").mkdir()
    nb = nbformat.read(FROM_PYTHON, as_version=4)
    client = NotebookClient(
        nb,
        timeout=900,
        kernel_name="python3",
        resources={"metadata": {"path": str(tmp_path / "notebooks")}},
    )
    client.execute()  # raises CellExecutionError, with the failing cell, if any cell fails
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    assert len([o for o in outputs if "image/png" in o.get("data", {})]) >= 2
    summary = tmp_path / "notebooks" / "runs" / "demo" / "quick" / "Pendulum-v1" / "test"
    assert (summary / "summary.csv").is_file()
    first = "".join(o.get("text", "") for o in nb.cells[0].outputs)
    assert "experiment 'demo' (variant quick)" in first


@pytest.mark.slow
def test_the_objects_notebook_evolves_trains_saves_and_reloads_a_model(tmp_path: Path) -> None:
    """As it is, in an empty folder, in about a minute on 2 cores."""
    nbformat = _nbformat()
    from nbclient import NotebookClient

    nb = nbformat.read(OBJECTS, as_version=4)
    client = NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError, with the failing cell, if any cell fails
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs)
    assert "Study 'CartPole-v1__all__20000steps', trials so far: 1" in text
    assert "7 trials; best fitness" in text
    assert "same returns as the trained model: True" in text
    saved = tmp_path / "runs" / "cartpole-model"
    assert sorted(p.name for p in saved.iterdir()) == ["model.json", "policy.pt"]
