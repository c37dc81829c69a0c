"""Evolving the Hebbian learner's genes (``evolve --learner hebbian``): the gene space, its
decoding into settings, the stored configuration, the CLI, the test phase's ``hebbian`` and
``random-hebbian`` agents, and replays that record the learner's state ``h``."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import optuna
import pytest

from ermrl.agents import resolve_ppo_config
from ermrl.config import (
    BudgetConfig,
    ConfigError,
    EncoderConfig,
    EvolveConfig,
    LearnerSpace,
    Problem,
    Range,
    SearchConfig,
    TaskConfig,
    from_dict,
    to_dict,
)
from ermrl.learners import default_agents, evolved_agent, get_learner, unevolved_agent
from ermrl.learners._hebbian import GENES

HEBBIAN = get_learner("hebbian")


def _ppo(env_id: str = "Pendulum-v1", **overrides: Any) -> Any:
    return resolve_ppo_config(env_id, overrides, learner="hebbian")


def _config(space: LearnerSpace | None = None, **problem: Any) -> EvolveConfig:
    ppo = _ppo()
    fields: dict[str, Any] = {
        "task": TaskConfig("Pendulum-v1"),
        "encoder": None,
        "ppo": ppo,
        "budget": BudgetConfig(training_steps=1000),
        **problem,
    }
    return EvolveConfig(
        problem=Problem(**fields),
        space=space or HEBBIAN.gene_space(ppo),
        search=SearchConfig(n_trials=3),
    )


def test_the_genes_are_the_issues_and_decode_to_settings() -> None:
    """Nine genes; tau_ratio and trace_horizon decode to tau_max and trace_decay, the rest are
    settings; decoding the default genes gives back the original's settings."""
    assert set(GENES) == {
        "spectral_radius", "input_scaling", "bias_scaling", "tau_min", "tau_ratio", "sigma",
        "trace_horizon", "learning_rate", "l2",
    }  # fmt: skip
    point = {name: r.low for name, r in GENES.items()} | {"tau_ratio": 4.0, "trace_horizon": 50.0}
    decoded = HEBBIAN.decode_genes(point)
    assert decoded["tau_max"] == pytest.approx(point["tau_min"] * 4.0)
    assert decoded["trace_decay"] == pytest.approx(0.98)
    assert "tau_ratio" not in decoded and "trace_horizon" not in decoded
    assert decoded["sigma"] == point["sigma"] and decoded["l2"] == point["l2"]
    ppo = _ppo()
    genes = HEBBIAN.gene_values(ppo)
    assert genes["tau_ratio"] == pytest.approx(4.0) and genes["trace_horizon"] == pytest.approx(100)
    settings = HEBBIAN.settings(ppo)
    again = HEBBIAN.settings(HEBBIAN.with_genes(ppo, genes))
    for key, value in settings.items():
        assert again[key] == pytest.approx(value), key


def test_the_gene_space_starts_from_the_studys_settings_and_clips_its_reference() -> None:
    ppo = _ppo(sigma=0.5)
    space = HEBBIAN.gene_space(ppo, {"sigma": Range(0.1, 0.9)})
    assert space.family == "hebbian" and space.param_names == tuple(GENES)
    assert space.ranges()["sigma"] == Range(0.1, 0.9)
    assert space.reference["sigma"] == 0.5 and space.reference["l2"] == 0.0
    ref = space.reference_params()
    assert space.contains(ref)
    assert ref["l2"] == GENES["l2"].low  # l2 0 lies below the log range: its nearest bound
    assert ref["spectral_radius"] == 0.95 and ref["learning_rate"] == 1e-4
    center = space.center_params()
    assert center["sigma"] == pytest.approx(math.sqrt(0.1 * 0.9))
    assert center["bias_scaling"] == pytest.approx(0.5)  # a linear range


@pytest.mark.parametrize(
    ("ranges", "message"),
    [
        ({"units": Range(10, 100)}, "learner 'hebbian' has no gene units"),
        ({"bias_scaling": Range(-1.0, 1.0, log=False)}, "hebbian bias_scaling must be >= 0"),
    ],
)
def test_bad_gene_ranges_are_refused_before_a_study(ranges: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        HEBBIAN.gene_space(_ppo(), ranges)


def test_a_learner_without_genes_has_no_gene_space() -> None:
    with pytest.raises(ConfigError, match="has no genes to evolve"):
        get_learner("ppo").gene_space(resolve_ppo_config("Pendulum-v1"))


def test_a_gene_study_configuration_round_trips_and_is_checked() -> None:
    config = _config()
    data = json.loads(json.dumps(to_dict(config)))
    assert data["problem"]["encoder"] is None and data["space"]["learner"] == "hebbian"
    back = from_dict(EvolveConfig, data)
    assert back == config and isinstance(back.space, LearnerSpace)
    assert back.default_study_name == "Pendulum-v1__all__1000steps__hebbian"
    with pytest.raises(ConfigError, match="has no encoder"):
        _config(encoder=EncoderConfig())
    with pytest.raises(ConfigError, match="cannot evolve learner 'ppo'"):
        _config(ppo=resolve_ppo_config("Pendulum-v1"))


def test_a_candidate_decodes_to_its_learner_settings_without_encoder() -> None:
    from ermrl.search import decode_candidate

    config = _config()
    point = config.space.center_params()
    encoder, problem = decode_candidate(config.space, point, config.problem)
    assert encoder is None
    hp = problem.ppo.hyperparams
    assert hp["sigma"] == pytest.approx(point["sigma"])
    assert hp["tau_max"] == pytest.approx(point["tau_min"] * point["tau_ratio"])
    assert hp["trace_decay"] == pytest.approx(1 - 1 / point["trace_horizon"])
    assert problem.task == config.problem.task and problem.seeds == config.problem.seeds
    with pytest.raises(ConfigError, match="gene 'sigma' missing"):
        decode_candidate(
            config.space, {k: v for k, v in point.items() if k != "sigma"}, config.problem
        )


def test_the_agents_of_a_gene_study() -> None:
    assert evolved_agent("hebbian") == "hebbian"
    assert unevolved_agent("hebbian") == "random-hebbian"
    assert default_agents("all", "hebbian") == ("ppo", "hebbian", "random-hebbian")
    assert "hebbian" not in default_agents("positions", "esn")


def _cli(*args: str, timeout: int = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args], capture_output=True, text=True, timeout=timeout
    )


def test_evolve_the_genes_then_test_hebbian_random_hebbian_and_ppo(tmp_path: Path) -> None:
    """A real evolution of the genes (SQLite), then ``test --agents hebbian random-hebbian ppo``:
    each agent trains with the settings it stands for, and replays record ``h``."""
    storage = f"sqlite:///{tmp_path / 'h.db'}"
    evolve = _cli(
        "evolve", "--env-id", "Pendulum-v1", "--observe", "positions", "--learner", "hebbian",
        "--ppo", "units=20", "--gene", "sigma=0.05:0.5", "--n-trials", "3", "--n-seeds", "1",
        "--training-steps", "400", "--storage", storage, "--study-name", "h",
    )  # fmt: skip
    assert evolve.returncode == 0, evolve.stderr
    study = optuna.load_study(study_name="h", storage=storage)
    trials = study.get_trials()
    assert len(trials) == 3 and all(set(t.params) == set(GENES) for t in trials)
    # The default genes compete as the first trial (l2 clipped into its box).
    assert trials[0].params["sigma"] == 0.25
    assert trials[0].params["trace_horizon"] == pytest.approx(100)
    assert all(0.05 <= t.params["sigma"] <= 0.5 for t in trials)
    fitness = [t.value for t in trials]
    assert len(set(fitness)) == 3, fitness  # the genes reach the learner
    best = study.best_trial

    out = tmp_path / "test"
    test = _cli(
        "test", "--study-name", "h", "--storage", storage, "--training-steps", "400",
        "--seeds", "10", "--agents", "hebbian", "random-hebbian", "ppo", "--out", str(out),
    )  # fmt: skip
    assert test.returncode == 0, test.stderr
    settings = {p.parent.parent.name: json.loads(p.read_text()) for p in out.rglob("settings.json")}
    assert set(settings) == {"hebbian", "random-hebbian", "ppo"}
    evolved = settings["hebbian"]["ppo"]["hyperparams"]
    default = settings["random-hebbian"]["ppo"]["hyperparams"]
    assert (
        settings["hebbian"]["encoder"] is None
        and settings["hebbian"]["ppo"]["learner"] == "hebbian"
    )
    assert evolved["sigma"] == pytest.approx(best.params["sigma"])
    assert evolved["tau_max"] == pytest.approx(best.params["tau_min"] * best.params["tau_ratio"])
    assert evolved["units"] == default["units"] == 20  # the study's fixed settings stay
    assert default["sigma"] == 0.25 and default["l2"] == 0.0 and default["trace_decay"] == 0.99
    assert settings["ppo"]["ppo"].get("learner", "ppo") == "ppo"

    from ermrl.analysis import load_trained_agent, rollout
    from ermrl.learners._hebbian_model import load_npz

    episode = rollout(load_trained_agent(out, "hebbian", 10), max_steps=30)
    assert episode.states.shape == (30, 20)
    # The recorded states are the agent's own h_t, by hand from its saved arrays.
    _, arrays = load_npz((out / "agents" / "hebbian" / "seed_10" / "model.zip").read_bytes())
    h = np.zeros(20)
    for t in range(3):
        pre = arrays["J"] @ h + arrays["J_in"] @ episode.observations[t] + arrays["b"]
        h = arrays["alpha"] * h + (1 - arrays["alpha"]) * np.tanh(pre)
        np.testing.assert_allclose(episode.states[t], h, rtol=1e-6, atol=1e-9)
    assert np.abs(episode.states).max() > 0

    refused = _cli(
        "test", "--study-name", "h", "--storage", storage, "--training-steps", "300",
        "--seeds", "10", "--agents", "res-ppo", "--out", str(tmp_path / "refused"),
    )  # fmt: skip
    assert refused.returncode == 2
    assert "\n" not in refused.stderr.strip() and "--encoder reservoir" in refused.stderr


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--learner", "hebbian", "--sr-range", "0.1", "2"], "--sr-range sets an evolved encoder"),
        (["--learner", "hebbian", "--encoder", "rtu"], "--encoder sets an evolved encoder"),
        (["--learner", "hebbian", "--gene", "nope=1:2"], "unknown gene 'nope'"),
        (["--learner", "hebbian", "--gene", "sigma=0.1"], "--gene expects NAME=LOW:HIGH"),
        (["--learner", "hebbian", "--gene", "sigma=0.5:0.1"], "low must be < high"),
        (["--learner", "hebbian", "--gene", "l2=0:1:log"], "a log-scale range needs low > 0"),
        (["--gene", "sigma=0.1:0.5"], "learner 'ppo' has none"),
    ],
)
def test_bad_gene_flags_are_refused_in_one_line_before_any_storage_exists(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], flags: list[str], message: str
) -> None:
    from ermrl.cli._evolve import evolve_main

    db = tmp_path / "x.db"
    with pytest.raises(SystemExit) as exit_:
        evolve_main(["--env-id", "Pendulum-v1", *flags, "--storage", f"sqlite:///{db}"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not db.exists()


def test_evolve_generalization_refuses_a_learner_with_genes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from ermrl.cli._generalization import evolve_generalization_main

    with pytest.raises(SystemExit) as exit_:
        evolve_generalization_main(
            ["--env-ids", "Pendulum-v1", "CartPole-v1", "--learner", "hebbian",
             "--storage", f"sqlite:///{tmp_path / 'x.db'}"]
        )  # fmt: skip
    assert exit_.value.code == 2
    assert "genes are evolved on one task with evolve" in capsys.readouterr().err
