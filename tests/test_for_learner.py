"""``--for-learner LEARNER KEY=VALUE ...``: settings of one learner only, and the DAgger agents.

``--ppo`` reaches every agent of a test phase, so a setting that other learners refuse (the
``dagger`` learner's ``expert``) goes to its learner only with ``--for-learner``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from ermrl.cli._common import for_learner_names, learner_overrides, parse_for_learner
from ermrl.cli._evolve import build_evolve_parser, evolve_main, learner_flags
from ermrl.cli._generalization import (
    build_evolve_generalization_parser,
    build_test_generalization_parser,
    evolve_generalization_main,
)
from ermrl.cli._generalization import test_generalization_main as run_test_generalization
from ermrl.cli._test import build_test_parser
from ermrl.cli._test import test_main as run_test
from ermrl.config import ConfigError
from ermrl.learners import AGENT_KINDS, default_agents, learner_names
from ermrl.test_phase._prepare import agent_learners

PENDULUM = "Pendulum-v1"

PARSERS: dict[str, Callable[[], argparse.ArgumentParser]] = {
    "test": build_test_parser,
    "test-generalization": build_test_generalization_parser,
    "evolve": build_evolve_parser,
    "evolve-generalization": build_evolve_generalization_parser,
}
REQUIRED: dict[str, list[str]] = {
    "test": ["--study-name", "s"],
    "test-generalization": ["--study-name", "s", "--env-id", PENDULUM],
    "evolve": ["--env-id", PENDULUM],
    "evolve-generalization": ["--env-ids", "Hopper-v5"],
}


def _cli(*args: str, cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _refused(
    main: Callable[[list[str]], int],
    argv: list[str],
    capsys: pytest.CaptureFixture[str],
    match: str,
) -> None:
    """``main(argv)`` exits 2 with one line on stderr that contains ``match``."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2, err[-2000:]
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert match in lines[0], lines[0]


# -- parsing and merging ----------------------------------------------------------------------


def test_values_are_read_as_ppo_values() -> None:
    name, settings = parse_for_learner(
        ["dagger", "expert=experts/hopper", "learning_rate=1e-4", "hidden_sizes=[32, 32]"]
    )
    assert name == "dagger"
    assert settings == {"expert": "experts/hopper", "learning_rate": 1e-4, "hidden_sizes": [32, 32]}
    assert parse_for_learner(["rtu-ppo", "stale_gradient=false"]) == (
        "rtu-ppo",
        {"stale_gradient": False},
    )


@pytest.mark.parametrize(
    ("words", "match"),
    [
        (["nope", "a=1"], "--for-learner nope: unknown learner 'nope'; choose from ppo"),
        (["dagger"], "--for-learner dagger: give at least one KEY=VALUE"),
        (["dagger", "expert"], "--for-learner dagger: 'expert' is not KEY=VALUE"),
        (["dagger", "=1"], "--for-learner dagger: '=1' is not KEY=VALUE"),
        (["dagger", "foo=1"], "--for-learner dagger: unknown setting 'foo' of learner 'dagger'"),
    ],
)
def test_bad_flags_are_refused_in_one_line(words: list[str], match: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_for_learner(words)
    assert str(err.value).startswith(match) and "\n" not in str(err.value)


def test_an_unknown_learner_lists_the_registered_ones() -> None:
    with pytest.raises(ConfigError, match=", ".join(learner_names())):
        parse_for_learner(["nope", "a=1"])


@pytest.mark.parametrize("command", list(PARSERS))
def test_every_command_takes_it_and_merges_it_with_stale_gradient(command: str) -> None:
    argv = [
        *REQUIRED[command],
        *("--for-learner", "dagger", "expert=a", "epochs=2"),
        "--no-stale-gradient",
        *("--for-learner", "rtu-ppo", "d_rec=8"),
        *("--for-learner", "dagger", "expert=b"),  # a later flag wins per key
    ]
    args = PARSERS[command]().parse_args(argv)
    assert learner_overrides(args) == {
        "dagger": {"expert": "b", "epochs": 2},
        "rtu-ppo": {"stale_gradient": False, "d_rec": 8},
    }
    assert for_learner_names(args) == ("dagger", "rtu-ppo")
    assert learner_overrides(PARSERS[command]().parse_args(REQUIRED[command])) == {}


@pytest.mark.parametrize("command", list(PARSERS))
def test_the_help_explains_it_with_an_example(command: str) -> None:
    text = " ".join(PARSERS[command]().format_help().split())
    assert "--for-learner LEARNER [KEY=VALUE ...]" in text
    assert "--for-learner dagger expert=experts/hopper" in text


@pytest.mark.parametrize("command", list(PARSERS))
def test_the_parsers_refuse_a_bad_flag_with_exit_2(
    command: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_:
        PARSERS[command]().parse_args([*REQUIRED[command], "--for-learner", "nope", "a=1"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--for-learner nope: unknown learner 'nope'" in err[0]


def test_evolve_applies_it_to_the_studys_learner_only() -> None:
    parser = build_evolve_parser()
    args = parser.parse_args(["--env-id", PENDULUM, "--for-learner", "dagger", "epochs=3"])
    assert learner_flags(args, "dagger") == {"epochs": 3}
    with pytest.raises(
        ConfigError,
        match=r"^--for-learner dagger: no agent of this run uses learner dagger \(the study "
        r"trains --learner ppo\)$",
    ):
        learner_flags(args, "ppo")


# -- the DAgger agents ------------------------------------------------------------------------


def test_the_dagger_agents_are_registered() -> None:
    dagger, res_dagger = AGENT_KINDS["dagger"], AGENT_KINDS["res-dagger"]
    assert (dagger.reservoirs, dagger.learner, dagger.family) == ("none", "dagger", None)
    assert (res_dagger.reservoirs, res_dagger.learner, res_dagger.family) == (
        "evolved",
        "dagger",
        "esn",
    )
    assert not dagger.default and not res_dagger.default
    assert "dagger" not in default_agents("positions")
    colors = [kind.color for kind in AGENT_KINDS.values()]
    assert len(set(colors)) == len(colors)
    assert agent_learners(["ppo", "res-ppo", "dagger", "res-dagger"], "ppo") == ("ppo", "dagger")


# -- refusals through the command line: exit 2, one line, nothing written --------------------


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["dagger", "epochs=2"], "--for-learner dagger: no agent of this run uses learner dagger"),
        (["ppo", "expert=x"], "'expert' is a setting of another learner (bc, dagger"),
        (["nope", "a=1"], "--for-learner nope: unknown learner 'nope'"),
    ],
)
@pytest.mark.parametrize("command", ["evolve", "evolve-generalization"])
def test_evolve_refuses_before_any_study(
    command: str,
    extra: list[str],
    match: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    db = tmp_path / "s.db"
    main = evolve_main if command == "evolve" else evolve_generalization_main
    argv = [*REQUIRED[command], "--storage", f"sqlite:///{db}", "--n-trials", "1"]
    _refused(main, [*argv, "--for-learner", *extra], capsys, match)
    assert not db.exists()


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A 2-trial ESN evolution with PPO on position-only Pendulum (20 units)."""
    tmp = tmp_path_factory.mktemp("for-learner")
    url = f"sqlite:///{tmp}/s.db"
    proc = _cli(
        "evolve", "--env-id", PENDULUM, "--observe", "positions", "--n-trials", "2",
        "--n-seeds", "1", "--training-steps", "400", "--storage", url, "--study-name", "s",
        "--sampler-seed", "1", "--n-envs", "1", "--units", "20", "--quiet",
        "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2",
        cwd=tmp,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    return tmp, url


def _test_args(url: str, out: Path, *extra: str) -> list[str]:
    return [
        "test", "--study-name", "s", "--storage", url, "--training-steps", "400",
        "--seeds", "10", "--out", str(out), "--no-save-models", "--quiet", *extra,
    ]  # fmt: skip


@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (
            ["--agents", "ppo", "res-ppo", "--for-learner", "dagger", "epochs=2"],
            "--for-learner dagger: no agent of this run uses learner dagger (agents ppo res-ppo "
            "use ppo)",
        ),
        (
            ["--agents", "ppo", "--for-learner", "ppo", "expert=x"],
            "'expert' is a setting of another",
        ),
        (["--agents", "ppo", "--for-learner", "ppo", "n_steps=0"], "n_steps must be >= 1"),
        (
            ["--agents", "dagger", "--for-learner", "dagger", "expert=x", "n_steps=64"],
            "'n_steps' is a setting of another learner (ppo",
        ),
        (["--agents", "dagger", "--for-learner", "dagger", "epochs=2"], "needs an expert"),
        # --ppo reaches every agent: the problem --for-learner solves
        (["--agents", "ppo", "dagger", "--ppo", "expert=x"], "does not take expert"),
    ],
)
def test_test_refuses_before_any_run(
    study: tuple[Path, str], extra: list[str], match: str, capsys: pytest.CaptureFixture[str]
) -> None:
    tmp, url = study
    out = tmp / "refused"
    _refused(run_test, _test_args(url, out, *extra)[1:], capsys, match)
    assert not out.exists()


def test_test_generalization_refuses_before_any_run(
    study: tuple[Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    tmp, url = study
    out = tmp / "refused-generalization"
    argv = _test_args(url, out, "--agents", "ppo", "--for-learner", "dagger", "epochs=2")[1:]
    _refused(
        run_test_generalization,
        [*argv, "--env-id", PENDULUM],
        capsys,
        "--for-learner dagger: no agent of this run uses learner dagger",
    )
    assert not out.exists()


def test_test_gives_the_dagger_agents_their_own_settings(
    study: tuple[Path, str],
    tiny_expert: Path,
) -> None:
    tmp, url = study
    out = tmp / "test"
    proc = _cli(
        *_test_args(url, out, "--agents", "ppo", "dagger", "res-dagger"),
        # beta 1 then 0 (beta_iterations=1): the last of the 400 steps' two episodes is the
        # imitator's alone, so the training return measures it
        *("--for-learner", "dagger", f"expert={tiny_expert}", "steps_per_iteration=200"),
        *("--for-learner", "dagger", "beta_iterations=1"),
        *("--for-learner", "dagger", "epochs=1"),
        cwd=tmp,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    settings: dict[str, Any] = {
        p.parent.parent.name: json.loads(p.read_text()) for p in out.rglob("settings.json")
    }
    assert set(settings) == {"ppo", "dagger", "res-dagger"}
    for agent in ("dagger", "res-dagger"):
        ppo = settings[agent]["ppo"]
        assert ppo["learner"] == "dagger"
        assert ppo["hyperparams"]["expert"] == str(tiny_expert)
        assert ppo["hyperparams"]["steps_per_iteration"] == 200
        assert ppo["hyperparams"]["epochs"] == 1
    ppo = settings["ppo"]["ppo"]
    assert ppo.get("learner", "ppo") == "ppo"  # left out of the record while the default
    assert ppo["hyperparams"]["n_steps"] == 128  # the study's
    assert not {"expert", "steps_per_iteration", "epochs"} & set(ppo["hyperparams"])
    assert settings["ppo"]["encoder"] is None and settings["dagger"]["encoder"] is None
    reservoirs = settings["res-dagger"]["encoder"]["reservoirs"]
    assert len(reservoirs) == 1 and reservoirs[0]["units"] == 20
