"""A study written before learners became plug-ins still loads and tests to the same returns."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data"


def test_a_study_written_by_the_old_code_tests_to_the_same_returns(tmp_path: Path) -> None:
    db = tmp_path / "study_v0.db"
    shutil.copy(DATA / "study_v0.db", db)  # the fixture itself is never written
    out = tmp_path / "out"
    cmd = [sys.executable, str(ROOT / "test.py"), "--study-name", "pendulum-v0"]
    cmd += ["--storage", f"sqlite:///{db}", "--agents", "ppo", "ppo-full", "res-ppo"]
    cmd += ["random-res-ppo", "--seeds", "5000", "--training-steps", "1024", "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    got = pd.read_csv(out / "curves.csv")
    want = pd.read_csv(DATA / "study_v0_curves.csv")
    # Same agents, seeds and episode ends exactly; returns to float32 accuracy. Torch's float32
    # kernels differ between CPUs (ATEN_CPU_CAPABILITY=default alone moves these returns), and
    # PPO's update amplifies the difference: on a second machine the same code reproduced the
    # fixture to 3.3e-6 (relative) in each agent's first episode (one PPO update in: n_steps 128)
    # and to 1.1e-3 in later ones. A wrong seed, mask, reservoir or initial policy changes the
    # first episode by far more than 1e-4 (the agents' first episodes here differ by 3% to 10%).
    pd.testing.assert_frame_equal(
        got.drop(columns="episode_return"), want.drop(columns="episode_return")
    )
    first = got.groupby("agent", sort=False).head(1).index
    pd.testing.assert_series_equal(
        got.loc[first, "episode_return"], want.loc[first, "episode_return"], rtol=1e-4
    )
    pd.testing.assert_series_equal(got["episode_return"], want["episode_return"], rtol=1e-2)
