"""The SLURM templates, submitted to a real single-node SLURM (``slurm/local_cluster.sh``).

The cluster is started here (installing ``slurm-wlm`` and ``munge`` from Debian when missing);
it needs root. When it cannot start the tests are skipped, unless ``ERMRL_REQUIRE_SERVICES=1``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

from ermrl.cli._study import study_main
from ermrl.storage import open_storage
from tests.conftest import unavailable

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SLURM = ROOT / "slurm"
N_TRIALS = 6
# Tiny trials: Pendulum with velocities hidden, 256 steps, one seed, a 20-unit reservoir.
# One trial per claim (--backend sb3), so that the 4 array tasks share the 6 trials: a population
# worker would claim a whole CMA-ES generation (7 candidates) alone.
TINY = ["--units", "20", "--n-envs", "1", "--ppo", "n_steps=128", "batch_size=64", "n_epochs=2"]
TINY += ["--backend", "sb3"]
WORKER = ["--heartbeat-interval", "2", "--grace-period", "20"]


@pytest.fixture(scope="module")
def slurm_env() -> Iterator[dict[str, str]]:
    """Environment for ``sbatch`` against the local cluster (started, and stopped if we did)."""
    if os.geteuid() != 0:
        unavailable("the local SLURM cluster needs root (SlurmUser=root)")
    script = str(SLURM / "local_cluster.sh")
    was_up = subprocess.run([script, "status"], capture_output=True).returncode == 0
    try:
        started = subprocess.run([script, "start"], capture_output=True, text=True, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as err:
        unavailable(f"slurm/local_cluster.sh start failed: {err}")
    match = re.search(r"export SLURM_CONF=(\S+)", started.stdout)
    if started.returncode != 0 or match is None:
        tail = (started.stderr or started.stdout).strip().splitlines()[-3:]
        unavailable(f"slurm/local_cluster.sh start failed: {' | '.join(tail)}")
    env = {**os.environ, "SLURM_CONF": match.group(1), "ERMRL_PYTHON": sys.executable}
    try:
        yield env
    finally:
        if not was_up and not os.environ.get("ERMRL_KEEP_SLURM"):
            subprocess.run([script, "stop"], capture_output=True)


def sbatch(env: dict[str, str], cwd: Path, *args: str, timeout: float = 300) -> str:
    """``sbatch --wait``: returns the job id once every array task has ended."""
    run = subprocess.run(
        ["sbatch", "--wait", "--time=15:00", "--mem=1G", *args],
        env=env,
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    logs = "\n".join(p.read_text()[-2000:] for p in sorted((cwd / "slurm" / "logs").glob("*")))
    assert run.returncode == 0, f"{run.stdout}{run.stderr}\n{logs}"
    match = re.search(r"Submitted batch job (\d+)", run.stdout)
    assert match, run.stdout
    return match.group(1)


@pytest.mark.parametrize(
    "fresh_storage",
    ["sqlite", pytest.param("postgresql", marks=pytest.mark.services)],
    indirect=True,
)
def test_evolve_array_then_test_array(
    slurm_env: dict[str, str], fresh_storage: str, tmp_path: Path
) -> None:
    (tmp_path / "slurm" / "logs").mkdir(parents=True)
    study_name = "slurm-test"
    # 1. Create the study once (README: before submitting the array).
    create = ["create", "--storage", fresh_storage, "--study-name", study_name, "--quiet"]
    create += ["--env-id", "Pendulum-v1", "--observe", "positions", "--n-seeds", "1"]
    create += ["--training-steps", "256", "--n-trials", str(N_TRIALS), *TINY]
    assert study_main(create) == 0

    # 2. Four workers on the shared study, through the real template.
    env = {
        **slurm_env,
        "ERMRL_STUDY": study_name,
        "ERMRL_STORAGE": fresh_storage,
        "ERMRL_ENV_ID": "Pendulum-v1",
        "ERMRL_OBSERVE": "positions",
        "ERMRL_N_TRIALS": str(N_TRIALS),
        "ERMRL_N_SEEDS": "1",
        "ERMRL_TRAINING_STEPS": "256",
    }
    job = sbatch(env, tmp_path, "--array=0-3", str(SLURM / "evolve_res.sbatch"), *TINY, *WORKER)
    logs = sorted((tmp_path / "slurm" / "logs").glob(f"ermrl-evolve_{job}_*.out"))
    assert [p.name for p in logs] == [f"ermrl-evolve_{job}_{i}.out" for i in range(4)]

    study = optuna.load_study(study_name=study_name, storage=open_storage(fresh_storage))
    trials = study.get_trials()
    states = Counter(t.state for t in trials)
    assert states == {TrialState.COMPLETE: N_TRIALS}, states
    tasks = {t.user_attrs["worker_slurm_array_task_id"] for t in trials}
    assert len(tasks) >= 2, tasks
    assert {t.user_attrs["worker_slurm_array_job_id"] for t in trials} == {job}

    if not fresh_storage.startswith("sqlite"):
        return  # the test array reads the study the same way on every backend
    # 3. The test phase: array task i trains on the i-th seed.
    out = tmp_path / "run"
    env.update(ERMRL_TEST_SEEDS="10 11", ERMRL_TEST_STEPS="256", ERMRL_OUT=str(out))
    test_args = ["--agents", "ppo", "res-ppo", "--no-save-models", "--quiet"]
    sbatch(env, tmp_path, "--array=0-1", str(SLURM / "test.sbatch"), *test_args)
    results = sorted(p.relative_to(out).as_posix() for p in out.rglob("result.json"))
    assert results == [
        f"agents/{agent}/seed_{seed}/result.json"
        for agent in ("ppo", "res-ppo")
        for seed in (10, 11)
    ]
    assert (out / "summary.csv").exists()


def test_an_experiment_file_evolution_array_then_the_rest_once(
    slurm_env: dict[str, str], tmp_path: Path
) -> None:
    """`ermrl run FILE --stage evolve` array tasks share the study; one more job finishes it."""
    import yaml

    (tmp_path / "slurm" / "logs").mkdir(parents=True)
    doc = {
        "name": "slurm-exp",
        "tasks": ["Pendulum-v1"],
        "evolve": {
            "observe": "positions", "units": 20, "n_trials": N_TRIALS, "n_seeds": 1,
            "training_steps": 256, "n_envs": 1, "popsize": 2,
            "ppo": {"n_steps": 128, "batch_size": 64, "n_epochs": 2},
            "heartbeat_interval": 2, "grace_period": 20,
        },
        "reevaluate": {"top": 1, "seeds": 1},
        "test": {"agents": ["ppo", "res-ppo"], "seeds": [10], "training_steps": 256},
        "report": {"dynamics": False, "interactive": False, "html": False},
    }  # fmt: skip
    path = tmp_path / "exp.yaml"
    path.write_text(yaml.safe_dump(doc))
    script = str(SLURM / "run_experiment.sbatch")
    env = {**slurm_env, "ERMRL_EXPERIMENT": str(path), "ERMRL_STAGE": "evolve"}
    job = sbatch(env, tmp_path, "--array=0-1", "--cpus-per-task=1", script)
    url = f"sqlite:///{tmp_path}/runs/slurm-exp/ermrl.db"
    study = optuna.load_study(
        study_name="Pendulum-v1__positions__256steps", storage=open_storage(url)
    )
    trials = study.get_trials()
    assert Counter(t.state for t in trials) == {TrialState.COMPLETE: N_TRIALS}
    assert {t.user_attrs["worker_slurm_array_job_id"] for t in trials} == {job}
    assert not (tmp_path / "runs" / "slurm-exp" / "Pendulum-v1" / "test").exists()
    env.pop("ERMRL_STAGE")
    sbatch(env, tmp_path, "--array=0", "--cpus-per-task=1", script)
    out = tmp_path / "runs" / "slurm-exp" / "Pendulum-v1"
    assert (out / "test" / "summary.csv").exists()
    assert (out / "report" / "report.md").exists()
    assert len(study.get_trials()) == N_TRIALS  # the final job trained no more trials
