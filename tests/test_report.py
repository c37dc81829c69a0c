"""``ermrl report`` and ``ermrl dynamics`` on a tiny HalfCheetah study and test phase."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ermrl.analysis import DynamicsRecording, write_report
from tests._analysis_data import TinyStudy, assert_self_contained_html, build_tiny_study

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
EVOLUTION_FIGURES = (
    "optimization_history",
    "param_importances",
    "param_slices",
    "param_contour",
    "cma_generations",
)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> TinyStudy:
    return build_tiny_study(tmp_path_factory.getbasetemp())


def ermrl(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args],
        cwd=cwd,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_report_cli_writes_figures_tables_and_report_md(tiny: TinyStudy, tmp_path: Path) -> None:
    out = tmp_path / "report"
    proc = ermrl(
        "report",
        "--study-name",
        tiny.study_name,
        "--storage",
        tiny.storage,
        "--runs",
        str(tiny.runs),
        "--out",
        str(out),
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "[report 1/" in proc.stdout and "ETA" in proc.stdout
    # The ETA is written as every other progress line of ermrl writes it ("1h02m", "3m05s").
    assert re.search(r"\[report 1/\d+\] .* \| ETA \d+m\d\ds$", proc.stdout, re.M), proc.stdout
    for name in EVOLUTION_FIGURES:
        assert (out / "evolution" / f"{name}.png").read_bytes().startswith(b"\x89PNG")
    for rel in ("test/learning_curves.png", "test/final_returns.png"):
        assert (out / rel).read_bytes().startswith(b"\x89PNG")
    assert list((out / "dynamics").glob("res-ppo_seed10_*.png"))
    assert (out / "dynamics" / "spectrum_comparison.png").exists()
    assert (out / "interactive" / "parallel_coordinate.html").exists()
    assert (out / "interactive" / "plotly.min.js").exists()
    md = (out / "report.md").read_text()
    for heading in (
        "## Study",
        "### Trials by state",
        "### Best parameters",
        "## Evolution",
        "## Test phase",
        "### `res-ppo` against the baselines",
        "## Reservoir dynamics",
        "## Appendix: the study's configuration",
    ):
        assert heading in md
    for rel in ("evolution/param_contour.png", "test/learning_curves.png"):
        assert f"]({rel})" in md
        assert (out / rel).exists()
    assert "single-task study" in md  # generalization left out, with the reason
    # Two test seeds: every interval is flagged, Welch's interval and p shown beside the bootstrap.
    for text in (
        "95% bootstrap CI",
        "95% Welch t CI",
        "p (Welch, two-sided)",
        "95% CI (Student t)",
    ):
        assert text in md
    assert "**Few seeds (n=2 < 5): every interval below is rough.**" in md
    assert md.count("| few seeds (n=2 < 5) |") >= 4  # agents and comparisons alike
    comparison = (out / "test" / "comparison.csv").read_text()
    assert "p_value" in comparison and "welch_ci_low" in comparison and "ppo" in comparison
    trials = (out / "trials.csv").read_text().splitlines()
    assert len(trials) == 5  # header + 4 trials
    # report.html is one file: moved alone, it still shows every figure (embedded PNGs).
    html = assert_self_contained_html(out / "report.html", tmp_path / "moved")
    for heading in ("<h2>Evolution</h2>", "<h3><code>res-ppo</code> against the baselines</h3>",
                    "<h2>Reservoir dynamics</h2>"):  # fmt: skip
        assert heading in html
    assert html.count("<img ") == md.count("![")
    assert "<strong>Few seeds (n=2 &lt; 5): every interval below is rough.</strong>" in html


def test_report_without_runs_still_writes_the_evolution_part(
    tiny: TinyStudy, tmp_path: Path
) -> None:
    result = write_report(
        tiny.study_name,
        tiny.storage,
        runs=tmp_path / "missing",
        out=tmp_path / "r",
        interactive=False,
        html_page=False,
    )
    assert result.html is None
    assert "param_slices" in result.figures and "learning_curves" not in result.figures
    assert any("test phase" in note and "does not exist" in note for note in result.notes)
    assert "## Test phase" not in result.markdown.read_text()


def test_report_of_a_missing_study_is_one_line_exit_2(tiny: TinyStudy, tmp_path: Path) -> None:
    proc = ermrl("report", "--study-name", "nope", "--storage", tiny.storage, cwd=tmp_path)
    assert proc.returncode == 2
    assert "no study named 'nope'" in proc.stderr and tiny.study_name in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_dynamics_cli_saves_arrays_figures_and_frequencies(tiny: TinyStudy, tmp_path: Path) -> None:
    proc = ermrl(
        "dynamics",
        "--run",
        str(tiny.runs),
        "--agent",
        "res-ppo",
        "--seed",
        "11",
        "--max-steps",
        "300",
        "--out",
        str(tmp_path),
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "dominant frequency of the reservoir states" in proc.stdout
    rec = DynamicsRecording.load(tmp_path / "res-ppo_seed11_episode.npz")
    assert rec.n_steps == 300 and rec.dt == pytest.approx(0.05)
    assert rec.states.shape == (300, 20) and rec.observations.shape == (300, 9)
    assert rec.actions.shape == (300, 6)
    assert np.abs(rec.states).max() <= 1.0 and np.abs(rec.states).max() > 0
    summary = json.loads((tmp_path / "res-ppo_seed11_spectrum.json").read_text())
    assert summary["frequency_unit"] == "Hz"
    assert set(summary["signals"]) == {"reservoir states", "observations", "actions"}
    for name in ("dynamics", "spectrum"):
        assert (tmp_path / f"res-ppo_seed11_{name}.png").read_bytes().startswith(b"\x89PNG")


def test_dynamics_of_a_missing_model_lists_the_available_ones(
    tiny: TinyStudy, tmp_path: Path
) -> None:
    proc = ermrl("dynamics", "--run", str(tiny.runs), "--seed", "99", cwd=tmp_path)
    assert proc.returncode == 2
    assert "res-ppo seed 10" in proc.stderr


def test_test_phase_tensorboard_option(tiny: TinyStudy, tmp_path: Path) -> None:
    args = [
        "test",
        "--study-name",
        tiny.study_name,
        "--storage",
        tiny.storage,
        "--agents",
        "ppo",
        "--seeds",
        "20",
        "--training-steps",
        "1024",
        "--out",
        str(tmp_path / "run"),
        "--tensorboard",
        str(tmp_path / "tb"),
        "--quiet",
    ]
    proc = ermrl(*args, cwd=tmp_path)
    if importlib.util.find_spec("tensorboard") is None:
        assert proc.returncode == 2
        assert "pip install tensorboard" in proc.stderr
        assert not (tmp_path / "run").exists()
    else:
        assert proc.returncode == 0, proc.stderr
        assert list((tmp_path / "tb" / "ppo" / "seed_20").rglob("events.out.tfevents.*"))
