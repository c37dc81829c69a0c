"""An env id read from a file (a run folder's ``config.yaml``, an expert's ``expert.json``) must
be a registered id: a ``module:Id`` there is refused in one line, and the module is never
imported (gymnasium would import it, running whatever it holds)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

EVIL_ID = "evilmod:Evil-v0"
EVIL_MODULE = """\
from pathlib import Path

Path(__file__).with_name("imported").write_text("evilmod ran")
"""


def _evil_folder(tmp_path: Path) -> Path:
    """A folder holding ``evilmod.py``, which writes ``imported`` next to it when imported."""
    (tmp_path / "evilmod.py").write_text(EVIL_MODULE)
    return tmp_path


def _run_folder(where: Path) -> Path:
    """A test-phase folder whose config.yaml names ``evilmod:Evil-v0``, with one saved run."""
    run = where / "run"
    seed = run / "agents" / "res-ppo" / "seed_3"
    seed.mkdir(parents=True)
    config = {
        "task": {"env_id": EVIL_ID, "observe": "all"},
        "ppo": {"hyperparams": {}},
        "encoder": {},
        "agents": {"res-ppo": [{"units": 10, "sr": 0.9, "lr": 0.5}]},
    }
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    (seed / "policy.pt").write_bytes(b"")
    (seed / "settings.json").write_text(json.dumps({"ppo": {"hyperparams": {}}}))
    return run


def _expert_folder(where: Path) -> Path:
    """An expert folder whose expert.json names ``evilmod:Evil-v0``."""
    from ermrl.config import PPOConfig
    from ermrl.experts import ExpertInfo

    info = ExpertInfo(
        env_id=EVIL_ID,
        algo="ppo",
        ppo=PPOConfig(),
        steps=64,
        env_steps=64,
        seed=0,
        wall_seconds=1.0,
        eval_returns=(0.0,),
        train_returns=(),
        observation_shape=(3,),
        action_shape=(1,),
        versions={},
    )
    expert = where / "expert"
    expert.mkdir()
    (expert / "expert.json").write_text(json.dumps(info.to_dict()))
    (expert / "policy.pt").write_bytes(b"")
    return expert


def _ermrl(cwd: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    """``python -m ermrl ...`` from ``cwd``, which is then first on ``sys.path``."""
    env = {**os.environ, "PYTHONPATH": str(cwd)}
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def _assert_refused(result: subprocess.CompletedProcess[str], where: Path, file: Path) -> None:
    assert result.returncode == 2, result.stderr
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1, err
    assert str(file) in err and EVIL_ID in err
    assert not (where / "imported").exists()


def _bare_study(where: Path) -> str:
    """A study (storage URL) with one completed trial, named ``s``."""
    import optuna

    url = f"sqlite:///{where / 'study.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="s", storage=url, direction="maximize")
    study.add_trial(
        optuna.trial.create_trial(
            params={"sr_0": 0.9},
            distributions={"sr_0": optuna.distributions.FloatDistribution(0.1, 2.0)},
            value=1.0,
        )
    )
    return url


def test_the_module_would_run_if_imported(tmp_path: Path) -> None:
    """The marker is live: importing evilmod from its folder writes it."""
    where = _evil_folder(tmp_path)
    subprocess.run([sys.executable, "-c", "import evilmod"], cwd=where, check=True)
    assert (where / "imported").exists()


def test_dynamics_refuses_a_module_env_id_in_config_yaml(tmp_path: Path) -> None:
    where = _evil_folder(tmp_path)
    run = _run_folder(where)
    result = _ermrl(where, "dynamics", "--run", str(run), "--out", str(where / "dyn"))
    _assert_refused(result, where, run / "config.yaml")
    assert not (where / "dyn").exists()


def test_video_refuses_a_module_env_id_in_config_yaml(tmp_path: Path) -> None:
    where = _evil_folder(tmp_path)
    run = _run_folder(where)
    result = _ermrl(where, "video", "--run", str(run), "--out", str(where / "video.mp4"))
    _assert_refused(result, where, run / "config.yaml")
    assert not (where / "video.mp4").exists()


def test_report_refuses_a_module_env_id_in_config_yaml(tmp_path: Path) -> None:
    where = _evil_folder(tmp_path)
    run = _run_folder(where)
    url = _bare_study(where)
    out = where / "report"
    result = _ermrl(
        where,
        "report",
        "--study-name",
        "s",
        "--storage",
        url,
        "--runs",
        str(run),
        "--out",
        str(out),
        "--no-interactive",
        "--no-html",
        "--quiet",
    )
    _assert_refused(result, where, run / "config.yaml")
    assert not out.exists()


def test_expert_eval_refuses_a_module_env_id_in_expert_json(tmp_path: Path) -> None:
    where = _evil_folder(tmp_path)
    expert = _expert_folder(where)
    out = where / "returns.csv"
    result = _ermrl(where, "expert", "eval", "--expert", str(expert), "--out", str(out))
    _assert_refused(result, where, expert / "expert.json")
    assert not out.exists()


def test_imitation_learner_refuses_a_module_env_id_in_expert_json(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from ermrl.config import ConfigError
    from ermrl.learners._dagger_model import load_expert_for

    where = _evil_folder(tmp_path)
    expert = _expert_folder(where)
    monkeypatch.syspath_prepend(str(where))
    monkeypatch.chdir(where)
    with pytest.raises(ConfigError) as info:
        load_expert_for(None, str(expert), "dagger")
    message = str(info.value)
    assert "\n" not in message and EVIL_ID in message and "expert.json" in message
    assert not (where / "imported").exists()
    assert "evilmod" not in sys.modules


def test_check_registered_env_id() -> None:
    from ermrl.envs import UnknownEnvError, check_registered_env_id

    check_registered_env_id("Pendulum-v1", "config.yaml")
    check_registered_env_id("AntNoContact-v5", "config.yaml")  # ermrl's own variant
    for bad in (EVIL_ID, "NoSuchEnv-v0", "", 3):
        with pytest.raises(UnknownEnvError, match="config.yaml"):
            check_registered_env_id(bad, "config.yaml")


def _evil_config() -> dict:
    """An ermrl study configuration (as stored in ``ermrl_config``) naming ``evilmod:Evil-v0``."""
    from ermrl.config import (
        BudgetConfig,
        EncoderConfig,
        EvolveConfig,
        PPOConfig,
        Problem,
        ReservoirSpace,
        SearchConfig,
        TaskConfig,
        to_dict,
    )

    space = ReservoirSpace(units=10)
    problem = Problem(
        task=TaskConfig("Pendulum-v1", "all"),
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        ppo=PPOConfig(hyperparams={"n_steps": 64, "batch_size": 32}),
        budget=BudgetConfig(training_steps=64),
        seeds=(0,),
    )
    data = to_dict(EvolveConfig(problem=problem, space=space, search=SearchConfig(n_trials=1)))
    data["problem"]["task"]["env_id"] = EVIL_ID
    return data


def _evil_study(where: Path) -> str:
    """A study whose stored configuration names ``evilmod:Evil-v0`` (an edited database)."""
    import optuna

    url = f"sqlite:///{where / 'evil.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="s", storage=url, direction="maximize")
    study.set_user_attr("ermrl_config", _evil_config())
    study.set_user_attr("ermrl_kind", "evolve")
    distribution = optuna.distributions.FloatDistribution(0.1, 2.0)
    study.add_trial(
        optuna.trial.create_trial(
            params={"sr": 1.0, "lr": 1.0, "input_scaling": 1.0},
            distributions={"sr": distribution, "lr": distribution, "input_scaling": distribution},
            value=1.0,
        )
    )
    return url


@pytest.mark.parametrize("agents", [[], ["--agents", "ppo-full"]])
def test_test_refuses_a_module_env_id_in_the_studys_stored_configuration(
    tmp_path: Path, agents: list[str]
) -> None:
    where = _evil_folder(tmp_path)
    url = _evil_study(where)
    out = where / "runs"
    result = _ermrl(
        where, "test", "--study-name", "s", "--storage", url, "--out", str(out), *agents
    )
    assert result.returncode == 2, result.stderr
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1, err
    assert "study 's'" in err and "stored configuration" in err and EVIL_ID in err
    assert not (where / "imported").exists()
    assert not out.exists()


def test_study_import_refuses_a_module_env_id_in_a_snapshots_configuration(
    tmp_path: Path,
) -> None:
    where = _evil_folder(tmp_path)
    url = _evil_study(where)
    snapshot = where / "study.json"
    exported = _ermrl(where, "study", "export", "--storage", url, "--study-name", "s", "--out",
                      str(snapshot))  # fmt: skip
    assert exported.returncode == 0, exported.stderr
    target = where / "target.db"
    result = _ermrl(where, "study", "import", "--storage", f"sqlite:///{target}", "--snapshot",
                    str(snapshot))  # fmt: skip
    assert result.returncode == 2, result.stderr
    err = result.stderr.strip()
    assert len(err.splitlines()) == 1, err
    assert str(snapshot) in err and EVIL_ID in err
    assert not (where / "imported").exists()
    assert not target.exists()


def test_check_stored_env_ids_walks_the_whole_configuration() -> None:
    from ermrl.config import ConfigError
    from ermrl.search import check_stored_env_ids

    check_stored_env_ids({"problem": {"task": {"env_id": "Pendulum-v1"}}}, "study 's'")
    nested = {"generalization": {"tasks": [{"task": {"env_id": "Pendulum-v1"}},
                                           {"task": {"env_id": EVIL_ID}}]}}  # fmt: skip
    with pytest.raises(ConfigError, match="study 's'.*evilmod"):
        check_stored_env_ids(nested, "study 's'")
    with pytest.raises(ConfigError, match="non-empty string"):
        check_stored_env_ids({"problem": {"task": {"env_id": 3}}}, "study 's'")
