"""Reference scores: the packaged table, random-policy episodic returns and the ``scores`` CLI."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import gymnasium
import pytest

from ermrl.cli._scores import scores_main
from ermrl.search import (
    MissingScoreError,
    ReferenceScore,
    load_scores,
    measure_random_returns,
    reference_returns,
    update_scores,
)
from ermrl.search._scores import (
    PROVISIONAL_TARGETS,
    REFERENCE_TARGETS,
    SCORE_COLUMNS,
    env_family,
    write_scores,
)

FAMILIES = ("Ant", "HalfCheetah", "Hopper", "Swimmer", "Walker2d")
MUJOCO_IDS = [f"{family}-v{v}" for family in FAMILIES for v in (4, 5)]


@pytest.mark.parametrize(
    ("env_id", "family"),
    [
        ("HalfCheetah-v5", "HalfCheetah"),
        ("Walker2d-v4", "Walker2d"),
        ("CartPole-v1", "CartPole"),
        ("ALE/Pong-v5", "Pong"),
        ("mymod:MyEnv-v0", "MyEnv"),
        ("NoVersion", "NoVersion"),
    ],
)
def test_env_family(env_id: str, family: str) -> None:
    assert env_family(env_id) == family


def test_packaged_table_has_measured_mujoco_rows_with_cited_targets() -> None:
    table = load_scores()
    assert set(MUJOCO_IDS) <= set(table)
    for env_id in MUJOCO_IDS:
        row = table[env_id]
        family = env_family(env_id)
        assert row.random_episodes == 100 and row.random_seed == 0
        assert row.gymnasium and row.random_std is not None and row.random_mean_length
        assert row.target == REFERENCE_TARGETS[family][0]
        assert "rl-baselines3-zoo" in row.target_source and f"{family}-v3" in row.target_source
        assert row.provisional_target == PROVISIONAL_TARGETS[family][0]
        assert "ER-MRL" in row.provisional_target_source
        # Episodic, not per-step: a 1000-step task's random return is far from a per-step mean.
        if family in ("HalfCheetah", "Swimmer"):
            assert row.random_mean_length == 1000.0
    assert table["HalfCheetah-v5"].random_mean < -100  # about -0.29 per step x 1000 steps


def test_reference_returns_and_clear_errors() -> None:
    table = {
        "A-v0": ReferenceScore("A-v0", random_mean=-1.0, target=9.0, provisional_target=4.0),
        "B-v0": ReferenceScore("B-v0", random_mean=2.0),
        "C-v0": ReferenceScore("C-v0", random_mean=3.0, target=3.0),
    }
    assert reference_returns("A-v0", table) == (-1.0, 9.0)
    assert reference_returns("A-v0", table, target_column="provisional_target") == (-1.0, 4.0)
    with pytest.raises(MissingScoreError, match=r"`ermrl scores --env-ids Z-v0 --out scores.csv`"):
        reference_returns("Z-v0", table)
    with pytest.raises(MissingScoreError, match="no target return for 'B-v0'"):
        reference_returns("B-v0", table)
    with pytest.raises(MissingScoreError, match="equals its random return"):
        reference_returns("C-v0", table)


def test_random_returns_are_episodic_sums_and_seeded() -> None:
    # CartPole pays 1 per step: an episodic return equals the episode length (a per-step mean
    # would be 1.0 for every episode).
    score = measure_random_returns("CartPole-v1", episodes=5, seed=3)
    assert list(score.returns) == [float(n) for n in score.lengths]
    assert score.mean > 5 and score.gymnasium == gymnasium.__version__
    again = measure_random_returns("CartPole-v1", episodes=5, seed=3)
    assert again.returns == score.returns
    assert measure_random_returns("CartPole-v1", episodes=5, seed=4).returns != score.returns


def test_update_keeps_targets_and_fills_known_families(tmp_path: Path) -> None:
    path = tmp_path / "scores.csv"
    write_scores(
        {"Hopper-v5": ReferenceScore("Hopper-v5", target=123.0, target_source="mine")}, path
    )
    hopper = measure_random_returns("Hopper-v5", episodes=2, seed=0)
    cartpole = measure_random_returns("CartPole-v1", episodes=2, seed=0)
    walker = measure_random_returns("Walker2d-v4", episodes=2, seed=0)
    update_scores([hopper, cartpole, walker], path)
    table = load_scores(path)
    assert table["Hopper-v5"].target == 123.0 and table["Hopper-v5"].target_source == "mine"
    assert table["Hopper-v5"].random_mean == pytest.approx(hopper.mean, abs=1e-3)
    assert table["Hopper-v5"].random_episodes == 2
    assert table["Walker2d-v4"].target == REFERENCE_TARGETS["Walker2d"][0]
    assert table["CartPole-v1"].target is None and table["CartPole-v1"].target_source == ""
    with path.open() as handle:
        assert tuple(next(csv.reader(handle))) == SCORE_COLUMNS


def test_cli_errors_are_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    for argv, message in [
        (["--suite", "nope"], "unknown suite 'nope'; available: ant_cheetah"),
        (["--env-ids", "Hoper-v5"], "unknown env id 'Hoper-v5'"),
        (["--env-ids", "Hopper-v5", "--env-version", "v4"], "--env-version applies to --suite"),
    ]:
        with pytest.raises(SystemExit) as exc:
            scores_main(argv)
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1


def test_cli_smoke_writes_table(tmp_path: Path) -> None:
    out = tmp_path / "scores.csv"
    proc = subprocess.run(
        [sys.executable, "-m", "ermrl", "scores", "--env-ids", "Acrobot-v1", "Hopper-v5"]
        + ["--episodes", "3", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    table = load_scores(out)
    # A new table starts from the packaged rows; the two measured ones are replaced.
    assert {"Acrobot-v1", "Hopper-v5"} <= set(table)
    assert table["Hopper-v5"].random_episodes == 3
    assert "Hopper-v5" in proc.stdout and "no target return for Acrobot-v1" in proc.stdout


_HEADER = ",".join(SCORE_COLUMNS)


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        (b"", "no env_id column"),
        (b"foo,bar\n1,2\n", "no env_id column"),
        (b"[1, 2]\n", "no env_id column"),
        (f"{_HEADER}\nCartPole-v1,abc,,,,,,,,,\n".encode(), "'random_mean' has a bad value 'abc'"),
        (f"{_HEADER}\nCartPole-v1,1,1,1.5,,,,,,,\n".encode(), "'random_episodes' has a bad value"),
        (f"{_HEADER}\nCartPole-v1,1,1,-3,,,,,,,\n".encode(), "'random_episodes' has a bad value"),
        (f"{_HEADER}\n,1,1,1,,,,,,,\n".encode(), "a row has no env_id"),
        (f"{_HEADER}\nCartPole-v1,nan,,,,,,,,,\n".encode(), "'random_mean' has a bad value 'nan'"),
        (f"{_HEADER}\nCartPole-v1,1,,,1e400,,,,,,\n".encode(), "'random_mean_length' has a bad"),
        (b"\xff\xfe\x00bad", "is not UTF-8 text"),
        (b"env_id\n" + b"x" * 200_000 + b"\n", "is not a CSV table"),
    ],
    ids=[
        "empty",
        "no-env-id",
        "json",
        "text",
        "float-int",
        "negative-int",
        "no-env",
        "nan",
        "overflow",
        "binary",
        "huge-field",
    ],
)
def test_cli_refuses_a_crafted_table_before_measuring(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    content: bytes,
    problem: str,
) -> None:
    """``--out`` naming a damaged or crafted table: one line naming the file and the problem,
    exit 2, before any episode is run, and the file left as it was (no temporary file)."""
    import ermrl.search._scores as scores_module

    def no_measuring(*args: object, **kwargs: object) -> None:
        raise AssertionError("measured before the table was checked")

    monkeypatch.setattr(scores_module, "measure_random_returns", no_measuring)
    out = tmp_path / "scores.csv"
    out.write_bytes(content)
    with pytest.raises(SystemExit) as exc:
        scores_main(["--env-ids", "CartPole-v1", "--episodes", "1", "--out", str(out), "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(out) in err and problem in err, err
    assert out.read_bytes() == content
    assert [p.name for p in tmp_path.iterdir()] == ["scores.csv"]


def test_cli_never_writes_into_the_installed_package(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without --out, scores.csv in the current folder starts as a copy of the packaged table."""
    from ermrl.search._scores import scores_path

    packaged = scores_path()
    before = packaged.read_bytes()
    monkeypatch.chdir(tmp_path)
    scores_main(["--env-ids", "CartPole-v1", "--episodes", "1", "--quiet"])
    assert packaged.read_bytes() == before
    table = load_scores(tmp_path / "scores.csv")
    assert set(load_scores(packaged)) | {"CartPole-v1"} == set(table)
    assert table["CartPole-v1"].random_episodes == 1
