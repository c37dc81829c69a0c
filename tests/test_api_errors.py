"""Bad calls of the Python API: one ConfigError line each, before anything is opened or written.

The calls are the ones a new user makes from the docs with the wrong types or names; each used
to leak an internal error (AttributeError, TypeError, NotADirectoryError, or a failure 14
frames into training) or to write a report from a folder that does not exist.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import ermrl


@pytest.fixture
def folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The working folder; the tests assert that nothing is written in it."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _url(folder: Path) -> str:
    return f"sqlite:///{folder / 's.db'}"


CASES: list[tuple[str, Any, str]] = [
    ("test seeds as a string", lambda u: ermrl.test("S", u, seeds="10"), "seeds: a list of integers"),
    ("test misspelled keyword", lambda u: ermrl.test("S", u, training_step=100),
     "did you mean 'training_steps'"),
    ("test options as a dict", lambda u: ermrl.test("S", u, options={}), "options is a TestOptions"),
    ("test storage as a number", lambda u: ermrl.test("S", 5), "storage is a storage URL"),
    ("test study as a number", lambda u: ermrl.test(5, u), "study_name is a study's name"),
    ("test agents typo", lambda u: ermrl.test("S", u, agents=["res-pop"]),
     "did you mean 'res-ppo'"),
    ("evolve with a number", lambda u: ermrl.evolve(42, u), "config is an env id"),
    ("evolve storage None", lambda u: ermrl.evolve("CartPole-v1", storage=None),
     "storage is a storage URL"),
    ("evolve in-memory storage", lambda u: ermrl.evolve("CartPole-v1", "sqlite://"),
     "storage:"),
    ("evolve misspelled option", lambda u: ermrl.evolve("CartPole-v1", u, n_trails=3),
     "did you mean 'n_trials'"),
    ("evolve trials as a string", lambda u: ermrl.evolve("CartPole-v1", u, n_trials="4"),
     "evolve CartPole-v1: n_trials: a number is expected, got str '4'"),
    ("evolve half a seed", lambda u: ermrl.evolve("CartPole-v1", u, n_seeds=1.5),
     "n_seeds: an integer is expected, got 1.5"),
    ("evolve a range of one", lambda u: ermrl.evolve("CartPole-v1", u, sr_range=[1.0]),
     "sr_range: 2 values are expected, got 1"),
    ("evolve observe typo", lambda u: ermrl.evolve("CartPole-v1", u, observe="position"),
     "did you mean 'positions'"),
    ("experiment from a number", lambda u: ermrl.Experiment.load(5), "a YAML file's path"),
    ("report band typo", lambda u: ermrl.report("S", u, band="ci9"), "did you mean 'ci95'"),
    ("report runs missing", lambda u: ermrl.report("S", u, runs="runs/nosuch"), "no such folder"),
]  # fmt: skip


@pytest.mark.parametrize(("case", "call", "expected"), CASES, ids=[c[0] for c in CASES])
def test_a_bad_call_raises_one_config_error_line_and_writes_nothing(
    folder: Path, case: str, call: Any, expected: str
) -> None:
    with pytest.raises(ermrl.ConfigError) as err:
        call(_url(folder))
    message = str(err.value)
    assert expected in message
    assert len(message.splitlines()) == 1, message
    assert list(folder.iterdir()) == []


def test_report_refuses_a_file_as_its_folder(folder: Path) -> None:
    report = folder / "report.md"
    report.write_text("mine")
    with pytest.raises(ermrl.ConfigError, match="a file, not a folder"):
        ermrl.report("S", _url(folder), out=report)
    assert report.read_text() == "mine" and sorted(folder.iterdir()) == [report]


def test_evolve_keywords_are_checked_by_the_schema_and_whole_numbers_pass() -> None:
    from ermrl.runner import evolve_config

    config = evolve_config(
        "CartPole-v1", n_trials=4.0, training_steps=1e4, fixed_input_scaling=True,
        ppo={"n_steps": 128}, sr_range=(0.1, 2),
    )  # fmt: skip
    assert config.search.n_trials == 4 and config.problem.budget.training_steps == 10_000
    assert config.space.input_scaling is None and config.space.fixed_input_scaling == 1.0
    assert (config.space.sr.low, config.space.sr.high) == (0.1, 2.0)
    assert config.problem.ppo.hyperparams["n_steps"] == 128
    with pytest.raises(ermrl.ConfigError, match="evolve CartPole-v1: reference_trial: true or"):
        evolve_config("CartPole-v1", reference_trial="no")  # not a text source


def test_test_options_take_the_same_checks_as_keywords() -> None:
    with pytest.raises(ermrl.ConfigError, match="TestOptions: seeds: a list of integers"):
        ermrl.TestOptions(seeds="10")
    options = ermrl.TestOptions(seeds=[10, 11.0], training_steps=1e4)  # whole numbers pass
    assert options.seeds == (10, 11) and options.training_steps == 10_000
