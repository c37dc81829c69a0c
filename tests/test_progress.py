"""Progress lines inside long work: when they come, what rate they show, and in a real test phase."""

from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ermrl._progress import Progress, default_mode, duration


class FakeTerminal(io.StringIO):
    """A stream that says it is a terminal, as a TTY stdout does."""

    def isatty(self) -> bool:
        return True


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_rate_excludes_start_up_and_lines_come_every_tenth_or_interval() -> None:
    clock, out = Clock(), io.StringIO()
    p = Progress("run", 10_000, interval=30.0, stream=out, clock=clock)
    clock.now = 100.0  # 100 s of start-up before the first step
    p.update(0)
    clock.now = 105.0
    p.update(500)  # 5%: no line yet
    assert p.lines == []
    clock.now = 110.0
    p.update(1_000)  # 10%: a line, at 100 steps/s (not 1000 / 110 s)
    assert p.lines == ["[run] 1,000/10,000 steps (10%) | 100 steps/s | ETA 1m30s"]
    clock.now = 145.0
    p.update(1_100)  # 35 s since the last line: a line although the next tenth is far
    assert len(p.lines) == 2 and "(11%)" in p.lines[-1]
    clock.now = 200.0
    p.update(10_000)
    p.close()  # the last update printed the final line: not twice
    assert p.lines[-1].startswith("[run] 10,000/10,000 steps (100%)") and len(p.lines) == 3
    assert out.getvalue().splitlines() == p.lines


def test_none_prints_nothing_and_bad_mode_is_refused() -> None:
    out = io.StringIO()
    p = Progress("run", 10, mode="none", stream=out)
    for i in range(11):
        p.update(i)
    p.close()
    assert out.getvalue() == ""
    with pytest.raises(ValueError, match="progress mode"):
        Progress("run", 10, mode="fancy")  # type: ignore[arg-type]


def test_duration() -> None:
    assert duration(59.6) == "1m00s" and duration(7260) == "2h01m" and duration(float("nan")) == "?"


def test_train_agent_reports_its_steps() -> None:
    from ermrl.agents import resolve_ppo_config, train_agent
    from ermrl.config import BudgetConfig, TaskConfig

    ppo = resolve_ppo_config(
        "CartPole-v1", {"n_steps": 64, "batch_size": 64, "n_epochs": 1}, n_envs=1
    )
    out = io.StringIO()
    progress = Progress("ppo seed 0", 640, stream=out)
    train_agent(
        TaskConfig("CartPole-v1", "all"),
        None,
        ppo,
        BudgetConfig(training_steps=640),
        0,
        progress=progress,
    )
    lines = out.getvalue().splitlines()
    assert len(lines) >= 9  # a line per tenth (each rollout of 64 steps is one)
    assert lines[-1].startswith("[ppo seed 0] 640/640 steps (100%)")
    assert all(re.search(r"\| \d+ steps/s \| ETA ", line) for line in lines)


def test_bar_mode_draws_a_tqdm_bar_with_the_total_and_a_rate_without_start_up() -> None:
    clock, out = Clock(), FakeTerminal()
    p = Progress("res-ppo seed 3", 5_000, mode="bar", stream=out, clock=clock)
    time.sleep(0.5)  # start-up: tqdm's clock runs, but the bar does not exist yet
    for done in range(0, 5_001, 500):
        p.update(done)
        time.sleep(0.01)
    p.close()
    text = out.getvalue()
    frames = [f for f in re.split(r"[\r\n]", text) if f.strip()]
    assert frames and all(f.startswith("res-ppo seed 3: ") for f in frames), text
    last = frames[-1]
    assert "100%" in last and "5000/5000" in last and " steps/s]" in last, last
    # ~5,000 steps in ~0.1 s: a rate counted from creation (0.6 s) would be under 10,000/s.
    rate = float(re.search(r", ([\d.]+) steps/s\]", last).group(1))  # type: ignore[union-attr]
    assert rate > 15_000, last
    assert text.endswith("\n")  # the finished bar stays on screen
    assert "[res-ppo seed 3]" not in text  # no lines besides the bar
    assert p.lines  # the lines that were due are still recorded, for callers


def test_train_agent_draws_its_bar_on_a_terminal() -> None:
    from ermrl.agents import resolve_ppo_config, train_agent
    from ermrl.config import BudgetConfig, TaskConfig

    ppo = resolve_ppo_config(
        "CartPole-v1", {"n_steps": 64, "batch_size": 64, "n_epochs": 1}, n_envs=1
    )
    out = FakeTerminal()
    progress = Progress("ppo seed 0", 640, mode="bar", stream=out)
    train_agent(
        TaskConfig("CartPole-v1", "all"), None, ppo, BudgetConfig(training_steps=640), 0,
        progress=progress,
    )  # fmt: skip
    last = [f for f in re.split(r"[\r\n]", out.getvalue()) if f.strip()][-1]
    assert last.startswith("ppo seed 0: 100%") and "640/640 [" in last, out.getvalue()


def _update_elsewhere(progress: Progress) -> tuple[str, list[str], str]:
    out = io.StringIO()
    sys.stdout = out  # this worker's stdout
    for done in range(0, 101, 10):
        progress.update(done)
    progress.close()
    return progress.shows, progress.lines, out.getvalue()


def test_a_bar_sent_to_a_worker_process_prints_lines_there() -> None:
    from concurrent.futures import ProcessPoolExecutor

    progress = Progress("trial 1, part 2/2", 100, mode="bar")
    assert progress.shows == "bar"
    with ProcessPoolExecutor(1) as pool:
        shows, lines, printed = pool.submit(_update_elsewhere, progress).result(timeout=120)
    assert shows == "lines" and len(lines) == 10
    assert printed.splitlines() == lines and lines[-1].startswith("[trial 1, part 2/2] 100/100")


def test_the_default_mode_is_a_bar_on_a_terminal_and_lines_elsewhere(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import argparse

    from ermrl.cli._common import progress_mode
    from ermrl.cli._evolve import build_evolve_parser
    from ermrl.cli._run import build_run_parser
    from ermrl.cli._test import build_test_parser

    assert default_mode(FakeTerminal()) == "bar" and default_mode(io.StringIO()) == "lines"
    for parser, argv in (
        (build_evolve_parser(), ["--env-id", "CartPole-v1"]),
        (build_test_parser(), ["--study-name", "s"]),
        (build_run_parser(), ["exp.yaml"]),
    ):
        assert parser.parse_args(argv).progress is None  # resolved after parsing
        assert parser.parse_args([*argv, "--progress", "lines"]).progress == "lines"
    monkeypatch.setattr(sys, "stdout", FakeTerminal())
    assert progress_mode(argparse.Namespace(progress=None)) == "bar"
    assert progress_mode(argparse.Namespace(progress="none")) == "none"
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    assert progress_mode(argparse.Namespace(progress=None)) == "lines"


def ermrl(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ermrl", *args], cwd=cwd, capture_output=True, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"}, timeout=600,
    )  # fmt: skip


def test_test_phase_prints_progress_inside_each_run(tmp_path: Path) -> None:
    names = ["--storage", f"sqlite:///{tmp_path}/s.db", "--study-name", "p"]
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "1", "--n-seeds", "1",
        "--training-steps", "128", "--n-envs", "1", "--units", "10",
        "--ppo", "n_steps=64", "batch_size=32", "n_epochs=1", *names, "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    common = [
        "test",
        *names,
        "--agents",
        "ppo",
        "res-ppo",
        "--seeds",
        "20",
        "--training-steps",
        "600",  # rounded up to whole rollouts of 64 steps: the lines count to 640
        "--backend",
        "sb3",  # the population backend reports per generation, not per run
    ]
    lines = ermrl(*common, "--out", "a", "--n-procs", "2", cwd=tmp_path)
    assert lines.returncode == 0, lines.stderr
    for agent in ("ppo", "res-ppo"):  # printed by the worker processes, one run each
        inside = [x for x in lines.stdout.splitlines() if x.startswith(f"[{agent} seed 20] ")]
        assert len(inside) >= 5 and "640/640 steps (100%)" in inside[-1], lines.stdout
    none = ermrl(*common, "--out", "b", "--progress", "none", cwd=tmp_path)
    assert none.returncode == 0, none.stderr
    assert not [x for x in none.stdout.splitlines() if x.startswith("[ppo seed 20] ")]
    assert "[run 2/2]" in none.stdout  # the finished-run lines stay


def test_run_lines_count_every_run_when_populations_and_other_learners_mix(
    tmp_path: Path,
) -> None:
    """A test phase whose PPO agents train as a population and whose framestack-ppo runs train
    one by one (sb3) numbers its finished runs 1..N over both, with a non-negative ETA."""
    import re

    names = ["--storage", f"sqlite:///{tmp_path}/s.db", "--study-name", "p"]
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "1", "--n-seeds", "1",
        "--training-steps", "128", "--n-envs", "1", "--units", "10", "--backend", "population",
        "--ppo", "n_steps=64", "batch_size=64", "n_epochs=1", *names, "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    proc = ermrl(
        "test", *names, "--agents", "ppo", "res-ppo", "framestack-ppo", "--seeds", "20", "21",
        "--training-steps", "256", "--n-procs", "1", "--progress", "none", "--out", "t",
        cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    runs = re.findall(r"^\[run (\d+)/(\d+)\] (\S+) .*ETA (\S+)$", proc.stdout, re.M)
    assert [(int(k), int(n)) for k, n, _, _ in runs] == [(k, 6) for k in range(1, 7)]
    assert {a for _, _, a, _ in runs[:4]} == {"ppo", "res-ppo"}  # the populations first
    assert [a for _, _, a, _ in runs[4:]] == ["framestack-ppo"] * 2
    assert not any(eta.startswith("-") for _, _, _, eta in runs), proc.stdout


def test_population_backend_prints_progress_per_population(tmp_path: Path) -> None:
    from ermrl.agents import resolve_ppo_config
    from ermrl.config import BudgetConfig, TaskConfig
    from ermrl.population import PopulationJob, train_population_parallel

    ppo = resolve_ppo_config(
        "CartPole-v1", {"n_steps": 64, "batch_size": 64, "n_epochs": 1}, n_envs=1
    )
    out = io.StringIO()
    progress = Progress("population of 3 runs", 640, stream=out, unit="steps each")
    results = train_population_parallel(
        TaskConfig("CartPole-v1", "all"), ppo, BudgetConfig(training_steps=640),
        [PopulationJob(None, s) for s in (1, 2, 3)], progress=progress,
    )  # fmt: skip
    assert len(results) == 3
    lines = out.getvalue().splitlines()
    assert len(lines) >= 9 and lines[-1].startswith(
        "[population of 3 runs] 640/640 steps each (100%) | "
    )


@pytest.mark.parametrize("backend", ["sb3", "population"])
def test_evolution_prints_progress_inside_each_trial(tmp_path: Path, backend: str) -> None:
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "2", "--n-seeds", "2",
        "--training-steps", "640", "--n-envs", "1", "--units", "10", "--backend", backend,
        "--ppo", "n_steps=64", "batch_size=64", "n_epochs=1",
        "--storage", f"sqlite:///{tmp_path}/s.db", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.splitlines()
    if backend == "sb3":  # each seed's run, labelled with its trial
        for trial in (0, 1):
            for seed in (0, 1):
                label = f"[trial {trial}, seed {seed} on CartPole-v1] "
                inside = [x for x in out if x.startswith(label)]
                assert len(inside) >= 5 and "640/640 steps (100%)" in inside[-1], proc.stdout
    else:  # the generation's population: 2 candidates x 2 seeds
        label = "[trials 0-1, 4 agents on CartPole-v1] "
        inside = [x for x in out if x.startswith(label)]
        assert len(inside) >= 5 and "640/640 steps each (100%)" in inside[-1], proc.stdout
    # the progress lines come before the trial's own line
    first_trial_line = next(i for i, x in enumerate(out) if x.startswith("[trial 0 | "))
    assert any(x.startswith("[trial") and ", " in x.split("]")[0] for x in out[:first_trial_line])
    quiet = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "1", "--n-seeds", "1",
        "--training-steps", "640", "--n-envs", "1", "--units", "10", "--backend", backend,
        "--ppo", "n_steps=64", "batch_size=64", "n_epochs=1", "--progress", "none",
        "--storage", f"sqlite:///{tmp_path}/q.db", cwd=tmp_path,
    )  # fmt: skip
    assert quiet.returncode == 0, quiet.stderr
    assert not [
        x for x in quiet.stdout.splitlines() if " steps/s | ETA " in x and "fitness" not in x
    ]


def _run_in_a_terminal(argv: list[str], cwd: Path, timeout: float = 600) -> tuple[int, str]:
    """Run ``argv`` with its stdout and stderr on a pseudo-terminal; its exit code and output."""
    import fcntl
    import pty
    import select
    import struct
    import termios

    main, child = pty.openpty()
    # A terminal 120 columns wide (a new pseudo-terminal has 0, where tqdm draws nothing).
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    proc = subprocess.Popen(
        argv, cwd=cwd, stdin=subprocess.DEVNULL, stdout=child, stderr=child,
        env={**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "120", "TERM": "xterm"},
    )  # fmt: skip
    os.close(child)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([main], [], [], 1.0)
        if ready:
            try:
                data = os.read(main, 65536)
            except OSError:  # the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    os.close(main)
    return proc.wait(timeout=60), b"".join(chunks).decode(errors="replace")


def test_a_population_on_two_processes_draws_one_bar_on_a_terminal(tmp_path: Path) -> None:
    """On a terminal, the parts of a population trained in 2 processes report to the parent,
    which draws one bar (tqdm) to 100%; no per-part lines from the workers."""
    names = ["--storage", f"sqlite:///{tmp_path}/s.db", "--study-name", "p"]
    proc = ermrl(
        "evolve", "--env-id", "CartPole-v1", "--n-trials", "1", "--n-seeds", "1",
        "--training-steps", "128", "--n-envs", "1", "--units", "10", "--backend", "population",
        "--ppo", "n_steps=64", "batch_size=64", "n_epochs=1", *names, "--quiet", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    code, out = _run_in_a_terminal(
        [sys.executable, "-m", "ermrl", "test", *names, "--agents", "res-ppo", "--seeds",
         "20", "21", "22", "23", "--training-steps", "1280", "--backend", "population",
         "--n-procs", "2", "--out", "t"],
        cwd=tmp_path,
    )  # fmt: skip
    assert code == 0, out
    frames = [f for f in re.split(r"[\r\n]", out) if f.strip()]
    bars = [f for f in frames if f.startswith("population of 4 runs (res-ppo):")]
    assert bars and "100%" in bars[-1] and "1280/1280" in bars[-1], out
    assert "part 1/2" not in out and "part 2/2" not in out, out
