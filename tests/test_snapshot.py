"""ermrl.storage snapshots: a study (and its re-evaluation study) through one plain JSON file, into
another storage, and an evolution that resumes there where it stopped."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import warnings
from pathlib import Path
from typing import Any

import optuna
import pytest
from optuna.trial import TrialState, create_trial

from ermrl.cli import evolve_main
from ermrl.cli._study import study_main
from ermrl.search import (
    create_or_resume_study,
    reevaluate_study,
    reevaluation_study_name,
    run_evolution,
    sample_params,
)
from ermrl.search._study import search_distributions
from ermrl.storage import (
    HEARTBEAT_ATTR,
    RELATED_SUFFIXES,
    SNAPSHOT_FORMAT,
    SnapshotError,
    StudyExists,
    import_snapshot,
    load_snapshot,
    open_storage,
    read_snapshot,
    study_to_snapshot,
    write_snapshot,
)
from ermrl.storage._snapshot import _canonical
from tests.test_storage import stub_fitness, tiny_config

optuna.logging.set_verbosity(optuna.logging.WARNING)

ROOT = Path(__file__).resolve().parents[1]
FIELDS = (
    "number",
    "state",
    "values",
    "datetime_start",
    "datetime_complete",
    "params",
    "distributions",
    "user_attrs",
    "system_attrs",
    "intermediate_values",
)
# A real evolution small enough for a test (as tests/test_cli.py): popsize 2, so that 4 trials
# are two CMA-ES generations and the optimizer state is stored on trial 2.
EVOLVE = [
    *("--env-id", "Pendulum-v1", "--observe", "positions", "--n-seeds", "1"),
    *("--training-steps", "256", "--popsize", "2", "--sampler-seed", "0"),
    *("--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2", "--units", "20"),
    "--quiet",
]


def _jsonable(value: Any) -> str:
    """Canonical JSON (NaN equals NaN, tuples equal lists, -0.0 equals 0.0: SQLite keeps 0.0)."""
    if isinstance(value, dict):
        value = {k: v for k, v in value.items() if k != HEARTBEAT_ATTR}  # journal workers' own
    return json.dumps(_canonical(value), sort_keys=True, default=str)


def assert_same_trials(a: optuna.Study, b: optuna.Study) -> None:
    """Every trial of ``a`` equals that of ``b``, field by field."""
    ta, tb = a.get_trials(deepcopy=False), b.get_trials(deepcopy=False)
    assert len(ta) == len(tb)
    for x, y in zip(ta, tb):
        for field in FIELDS:
            assert _jsonable(getattr(x, field)) == _jsonable(getattr(y, field)), (x.number, field)


def assert_same_study(a: optuna.Study, b: optuna.Study) -> None:
    assert a.directions == b.directions
    assert _jsonable(a.user_attrs) == _jsonable(b.user_attrs)
    sa = a._storage.get_study_system_attrs(a._study_id)
    sb = b._storage.get_study_system_attrs(b._study_id)
    assert _jsonable(sa) == _jsonable(sb)
    assert_same_trials(a, b)


def varied_study(url: str, name: str = "demo") -> optuna.Study:
    """A CMA-ES study (stub fitness) with every trial state, odd floats, and a re-evaluation."""
    config = tiny_config(n_trials=5, popsize=2, sampler_seed=0, reevaluate_top=2)
    study = create_or_resume_study(config, url, name)
    run_evolution(config, study, quiet=True, evaluate=stub_fitness())
    doc = reevaluate_study(
        config, study, url, evaluator_factory=lambda c: stub_fitness(), quiet=True
    )
    assert doc is not None and doc["complete"]
    params = config.space.center_params()
    dists = search_distributions(config.space)
    study.add_trial(
        create_trial(
            state=TrialState.PRUNED,
            params=params,
            distributions=dists,
            intermediate_values={128: -1e3, 256: -math.inf},
            user_attrs={"returns_last": [1.5, math.nan]},
        )
    )
    study.add_trial(
        create_trial(
            state=TrialState.FAIL,
            params=params,
            distributions=dists,
            intermediate_values={128: math.nan},
            user_attrs={"fail_reason": "diverged"},
        )
    )
    study.enqueue_trial(params, user_attrs={"queued": True})
    study.set_user_attr("note", {"nested": [1, 2.5, None, "é"]})
    study._storage.set_study_system_attr(study._study_id, "system_note", [1, 2])
    return study


def _running_trial(study: optuna.Study) -> int:
    """Start a trial as a worker does (every parameter asked) and leave it RUNNING."""
    with warnings.catch_warnings():  # "Heartbeat ... used with Study.optimize": as ermrl's claim
        warnings.simplefilter("ignore", UserWarning)
        trial = study.ask()
    sample_params(trial, tiny_config().space)
    trial.set_user_attr("worker_pid", 12345)
    return trial.number


# -- the round trip ------------------------------------------------------------------------------


@pytest.mark.parametrize("fresh_storage", ["sqlite", "journal"], indirect=True)
def test_round_trip_keeps_every_field_of_every_trial(tmp_path: Path, fresh_storage: str) -> None:
    source = varied_study(f"sqlite:///{tmp_path}/source.db")
    path = tmp_path / "demo.json"
    doc = write_snapshot(source, path)
    text = path.read_text()
    assert json.loads(text)["format"] == SNAPSHOT_FORMAT and text.endswith("\n")
    assert list(doc["related"]) == ["demo.reeval"]
    assert not list(tmp_path.glob(".demo.json*"))  # the temporary file was renamed

    result = import_snapshot(path, fresh_storage)
    assert result.created == ("demo", "demo.reeval") and result.identical == ()
    assert result.interrupted == ()
    assert_same_study(source, result.study)
    states = [t.state for t in result.study.trials]
    assert states[-3:] == [TrialState.PRUNED, TrialState.FAIL, TrialState.WAITING]
    rstudy = optuna.load_study(study_name="demo.reeval", storage=open_storage(fresh_storage))
    source_reeval = optuna.load_study(study_name="demo.reeval", storage=source._storage)
    assert_same_study(source_reeval, rstudy)
    assert len(rstudy.trials) == 2  # the top 2 (the reference among them)
    # Exported again, the import gives the same document (only the export time differs).
    again = study_to_snapshot(result.study)
    for key in ("exported_at",):
        again.pop(key), doc.pop(key)
    assert _jsonable(again) == _jsonable(doc)


def test_reeval_is_the_only_related_suffix_and_matches_search() -> None:
    assert RELATED_SUFFIXES == (".reeval",)
    assert reevaluation_study_name("pend") == "pend" + RELATED_SUFFIXES[0]


def test_import_under_another_name_renames_the_reevaluation_study(tmp_path: Path) -> None:
    source = varied_study(f"sqlite:///{tmp_path}/source.db")
    path = tmp_path / "demo.json"
    write_snapshot(source, path)
    url = f"sqlite:///{tmp_path}/target.db"
    study = load_snapshot(path, url, study_name="pend2")
    assert study.study_name == "pend2"
    assert sorted(optuna.get_all_study_names(url)) == ["pend2", "pend2.reeval"]
    assert_same_trials(source, study)


@pytest.mark.parametrize("fresh_storage", ["sqlite", "journal"], indirect=True)
def test_real_evolution_resumes_where_it_stopped(tmp_path: Path, fresh_storage: str) -> None:
    """Evolve 4 trials, export, import, evolve to 6: the new trials are those the original
    storage would have run (same numbers, same CMA-ES generation, same points)."""
    source_db = tmp_path / "source.db"
    source = f"sqlite:///{source_db}"
    assert (
        evolve_main([*EVOLVE, "--storage", source, "--study-name", "pend", "--n-trials", "4"]) == 0
    )
    path = tmp_path / "pend.json"
    assert (
        study_main(["export", "--storage", source, "--study-name", "pend", "--out", str(path)]) == 0
    )
    # The run that never moved: the original database, continued.
    shutil.copy(source_db, tmp_path / "continued.db")
    continued_url = f"sqlite:///{tmp_path}/continued.db"
    assert (
        evolve_main(
            [*EVOLVE, "--storage", continued_url, "--study-name", "pend", "--n-trials", "6"]
        )
        == 0
    )

    assert study_main(["import", "--storage", fresh_storage, "--snapshot", str(path)]) == 0
    imported = optuna.load_study(study_name="pend", storage=open_storage(fresh_storage))
    original = optuna.load_study(study_name="pend", storage=source)
    assert_same_study(original, imported)
    assert (
        evolve_main(
            [*EVOLVE, "--storage", fresh_storage, "--study-name", "pend", "--n-trials", "6"]
        )
        == 0
    )

    resumed = optuna.load_study(study_name="pend", storage=open_storage(fresh_storage)).trials
    continued = optuna.load_study(study_name="pend", storage=continued_url).trials
    assert [t.number for t in resumed] == list(range(6))
    assert all(t.state == TrialState.COMPLETE for t in resumed)
    generations = [t.system_attrs["cma:restart_0:generation"] for t in resumed]
    assert generations == [0, 0, 1, 1, 2, 2]  # generation 2 follows, not a fresh generation 0
    assert {t.system_attrs["cma:n_restarts"] for t in resumed} == {0}
    # Generation 1 was told to the optimizer restored from trial 2's stored state.
    assert any(k.startswith("cma:state:") for k in resumed[4].system_attrs)
    for new, old in zip(resumed[4:], continued[4:]):
        assert new.params == old.params
        assert _jsonable(new.system_attrs) == _jsonable(old.system_attrs)
    # The stored configuration is that of the first sitting (no second reference trial).
    assert sum(bool(t.user_attrs.get("reference")) for t in resumed) == 1


# -- trials that were running --------------------------------------------------------------------


@pytest.mark.parametrize(("max_retry", "retried"), [(3, True), (0, False)])
def test_a_running_trial_comes_back_as_fail_and_is_retried(
    tmp_path: Path, max_retry: int, retried: bool
) -> None:
    source = f"journal:///{tmp_path}/source.log"
    config = tiny_config(n_trials=4, sampler="random", sampler_seed=0)
    study = create_or_resume_study(config, source, "demo")
    run_evolution(tiny_config(n_trials=3), study, quiet=True, evaluate=stub_fitness())
    number = _running_trial(study)
    path = tmp_path / "demo.json"
    write_snapshot(study, path)

    url = f"sqlite:///{tmp_path}/target.db"
    result = import_snapshot(path, url, max_retry=max_retry)
    trials = result.study.trials
    assert trials[number].state == TrialState.FAIL and trials[number].values is None
    assert trials[number].params == study.trials[number].params
    reason = trials[number].user_attrs["fail_reason"]
    assert reason.startswith("running when the study was exported")
    assert not any(t.state == TrialState.RUNNING for t in trials)
    if not retried:
        assert len(trials) == 4 and reason.endswith("not retried")
        assert result.interrupted == (("demo", number, None),)
        return
    assert reason.endswith(f"retried as trial {number + 1}")
    assert result.interrupted == (("demo", number, number + 1),)
    retry = trials[number + 1]
    assert retry.state == TrialState.WAITING and retry.params == trials[number].params
    assert retry.user_attrs["retry_of"] == number and "worker_pid" not in retry.user_attrs
    assert retry.system_attrs["failed_trial"] == number
    # The next worker runs the retry first and the budget (4) holds: no fifth trial.
    summary = run_evolution(config, result.study, quiet=True, evaluate=stub_fitness())
    assert summary.trials_run == 1
    after = result.study.trials
    assert len(after) == 5 and after[number + 1].state == TrialState.COMPLETE
    assert after[number + 1].params == study.trials[number].params
    # Once the retry ran, the study is no longer what the import wrote: importing again refuses.
    with pytest.raises(StudyExists, match=f"trial {number + 1} differs"):
        import_snapshot(path, url, max_retry=max_retry)


# -- refusals ------------------------------------------------------------------------------------


def test_importing_twice_is_safe_and_another_study_of_that_name_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    url = f"sqlite:///{tmp_path}/s.db"
    study = varied_study(url)
    _running_trial(study)
    path = tmp_path / "demo.json"
    write_snapshot(study, path)
    target = f"sqlite:///{tmp_path}/target.db"
    argv = ["import", "--storage", target, "--snapshot", str(path)]
    assert study_main(argv) == 0
    out = capsys.readouterr().out
    assert "imported study 'demo' (9 trials)" in out and "'demo.reeval' (2 trials)" in out
    assert "was running at export: imported as FAIL, retried as trial 8" in out
    assert study_main(argv) == 0  # the same file again: nothing to do
    out = capsys.readouterr().out
    assert "'demo' in" in out and "identical to the snapshot: nothing to import" in out
    assert "'demo.reeval' in" in out and "imported" not in out
    assert len(optuna.load_study(study_name="demo", storage=target).trials) == 9

    # The source, exported again after one more trial: not the study in the target any more.
    study.tell(study.trials[-1].number, 1.0)
    write_snapshot(study, tmp_path / "later.json")
    before = (tmp_path / "target.db").read_bytes()
    with pytest.raises(SystemExit) as err:
        study_main(["import", "--storage", target, "--snapshot", str(tmp_path / "later.json")])
    message = capsys.readouterr().err.strip()
    assert err.value.code == 2 and "\n" not in message
    assert "study 'demo' already exists" in message and "trial 7 differs" in message
    assert (tmp_path / "target.db").read_bytes() == before
    # A study of another storage that merely shares the name is refused too.
    optuna.create_study(study_name="other", storage=f"sqlite:///{tmp_path}/third.db")
    with pytest.raises(StudyExists, match="'other' already exists .* study directions differ"):
        import_snapshot(path, f"sqlite:///{tmp_path}/third.db", study_name="other")


@pytest.fixture(scope="module")
def good_doc(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The snapshot of a 2-trial study, broken in a new way by each test."""
    url = f"sqlite:///{tmp_path_factory.mktemp('good')}/s.db"
    study = create_or_resume_study(tiny_config(n_trials=2), url, "demo")
    run_evolution(tiny_config(n_trials=2), study, quiet=True, evaluate=stub_fitness())
    return study_to_snapshot(study)


def _break(doc: dict[str, Any], how: str) -> str | dict[str, Any]:
    """A broken copy of a snapshot document (a string: the file's text)."""
    doc = json.loads(json.dumps(doc))
    trial = doc["trials"][1]
    if how == "not json":
        return '{"format": "ermrl-study-snapshot", "version": 1,'
    if how == "not an object":
        return "[1, 2]"
    if how == "other format":
        doc["format"] = "optuna-study"
    elif how == "unknown version":
        doc["version"] = 2
    elif how == "no trials":
        del doc["trials"]
    elif how == "trial without params":
        del trial["params"]
    elif how == "unknown state":
        trial["state"] = "DONE"
    elif how == "unknown distribution":
        trial["distributions"]["sr"] = {"name": "os.system", "attributes": {"command": "ls"}}
    elif how == "bad distribution":
        trial["distributions"]["sr"] = {"name": "FloatDistribution", "attributes": {"low": 2}}
    elif how == "distribution not json-like":
        trial["distributions"]["sr"] = "FloatDistribution(0, 1)"
    elif how == "param outside its distribution":
        trial["params"]["sr"] = 1e9
    elif how == "complete without values":
        trial["values"] = None
    elif how == "gap in numbers":
        trial["number"] = 5
    elif how == "bad date":
        trial["datetime_start"] = "yesterday"
    elif how == "minimize":  # resumed, the "best" trial would be the worst
        doc["directions"] = ["MINIMIZE"]
    elif how == "infinite value":  # imported, it would be the best, shown as "fitness -"
        trial["values"] = [math.inf]
    return doc


BROKEN = (
    ("not json", "is not JSON"),
    ("not an object", "a JSON object is expected"),
    ("other format", "'format' is 'optuna-study'"),
    ("unknown version", "format version 2 is not supported"),
    ("no trials", "has no 'trials'"),
    ("trial without params", "trial 1 has no 'params'"),
    ("unknown state", "unknown state 'DONE'"),
    ("unknown distribution", "is not a distribution Optuna can read"),
    ("bad distribution", "is not a distribution Optuna can read"),
    ("distribution not json-like", "is not a distribution Optuna can read"),
    ("param outside its distribution", "isn't contained in the distribution"),
    ("complete without values", "values should be set"),
    ("gap in numbers", "must be numbered 0, 1"),
    ("bad date", "datetime_start"),
    ("minimize", "'directions' is ['MINIMIZE']; ermrl's studies maximize"),
    ("infinite value", "trial 1: 'values' must be finite, got [inf]"),
)


@pytest.mark.parametrize(("how", "expected"), BROKEN, ids=[b[0] for b in BROKEN])
def test_an_invalid_snapshot_is_refused_in_one_line_and_writes_nothing(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    good_doc: dict[str, Any],
    how: str,
    expected: str,
) -> None:
    broken = _break(good_doc, how)
    path = tmp_path / "broken.json"
    path.write_text(broken if isinstance(broken, str) else json.dumps(broken))
    with pytest.raises(SnapshotError, match="broken.json"):
        read_snapshot(path)
    target = tmp_path / "target.db"
    with pytest.raises(SystemExit) as err:
        study_main(["import", "--storage", f"sqlite:///{target}", "--snapshot", str(path)])
    message = capsys.readouterr().err.strip()
    assert err.value.code == 2 and "\n" not in message, message
    assert message.startswith("ermrl study import: error:") and expected in message, message
    assert not target.exists() and not Path(f"{target}.lock").exists()


def test_a_missing_snapshot_file_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as err:
        study_main(
            ["import", "--storage", f"{tmp_path}/t.log", "--snapshot", f"{tmp_path}/no.json"]
        )
    message = capsys.readouterr().err.strip()
    assert err.value.code == 2 and "cannot read snapshot" in message and "\n" not in message
    assert not (tmp_path / "t.log").exists()


# -- the command line, as a user runs it ---------------------------------------------------------


def test_cli_export_and_import_json_smoke(tmp_path: Path) -> None:
    source = f"sqlite:///{tmp_path}/s.db"
    varied_study(source)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}

    def ermrl(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "ermrl", "study", *args],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
        )  # fmt: skip

    help_ = ermrl("--help")
    assert help_.returncode == 0 and "--out pendulum.json" in help_.stdout
    assert "import" in help_.stdout and "--snapshot pendulum.json" in help_.stdout
    out = tmp_path / "x.json"
    proc = ermrl("export", "--storage", source, "--study-name", "demo", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "'demo' (8 trials), 'demo.reeval' (2 trials)" in proc.stdout
    target = f"journal:///{tmp_path}/t.log"
    proc = ermrl("import", "--storage", target, "--snapshot", str(out))
    assert proc.returncode == 0, proc.stderr
    assert f"imported study 'demo' (8 trials) into {target}" in proc.stdout
    proc = ermrl("import", "--storage", target, "--snapshot", str(out))
    assert proc.returncode == 0 and "identical" in proc.stdout, proc.stderr
    proc = ermrl("export", "--storage", source, "--study-name", "demo", "--out", "x.txt")
    assert proc.returncode == 2 and ".csv, .parquet, .jsonl or .json" in proc.stderr
    assert_same_trials(
        optuna.load_study(study_name="demo", storage=source),
        optuna.load_study(study_name="demo", storage=open_storage(target)),
    )
