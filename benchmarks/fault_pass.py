"""The reliability fault pass: every fault case of the last reliability round, rerun through the
real ``ermrl`` CLI, each in a fresh temporary folder, with tiny budgets.

Each case plants one fault (a hot SQLite journal, a signal mid-generation, an env id naming a
module in study data, glued journal records, a dangling lock, a malformed CMA-ES state, a
storage outage, a silent server, a full disk, a damaged checkpoint, a bad experiment file, a
crafted policy, a closed pipe, ...), runs the commands a user would, and classifies what
happened:

- ``traceback``: "Traceback (most recent call last)" in any command's output;
- ``bricked``: after the fault (and the repair a user would run), a read-only command
  (``ermrl study export``) or the next ``evolve`` still fails;
- ``code-run``: a planted module wrote its marker file (an env id ``module:Env`` from data);
- ``files-left``: a command that failed (exit code not 0, nor a signal's) left files or folders
  it created or changed (the storage it was asked to open, and its lock files, aside);
- ``trials-lost``: COMPLETE trials before the fault that are not COMPLETE after the repair or
  rerun (and a reference trial that never completes after an interruption);
- ``hang``: a command ran past its case's timeout (killed);
- ``other``: the case's own check failed (a refusal that was accepted, a full disk reported as
  success, a wrong exit code), with the reason.

Cases that need root (a tmpfs for a full disk) or a server (PostgreSQL 127.0.0.1:5432 trust db
``test``, MariaDB/MySQL 127.0.0.1:3306 root, Redis 127.0.0.1:6379) are skipped when these are
not available. Servers are never stopped: outages go through a TCP proxy the pass stops and
starts, and Redis is paused with ``CLIENT PAUSE`` for at most 5 s.

Usage::

    python benchmarks/fault_pass.py                       # every case (~50 min on 2 cores)
    python benchmarks/fault_pass.py --cases broken-pipe   # cases whose family/name matches
    python benchmarks/fault_pass.py --quick               # three cheap cases
    python benchmarks/fault_pass.py --list                # the cases, without running them

Prints one line per case and a summary table, writes ``fault_pass.csv`` to ``--out`` (a new
temporary folder by default) and exits 1 when any count is not 0.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import re
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
TRACEBACK = "Traceback (most recent call last)"
SIGNAL_CODES = {130, 141, 143, -2, -9, -15}  # interrupted, not failed: they keep their work
COUNTS = ("traceback", "bricked", "code-run", "files-left", "trials-lost")
POSTGRES = ("127.0.0.1", 5432)
MYSQL = ("127.0.0.1", 3306)
REDIS = ("127.0.0.1", 6379)

# The cheapest evolution that runs: CartPole, 10 units, 128 steps, CMA-ES with popsize 2.
TINY = ["--n-envs", "1", "--ppo", "n_steps=64", "batch_size=64", "n_epochs=1", "--units", "10"]
EVOLVE = [
    *("--env-id", "CartPole-v1", "--n-seeds", "1", "--training-steps", "128"),
    *("--popsize", "2", "--sampler-seed", "0", "--study-name", "s", "--progress", "none"),
    *TINY,
]
# A tiny experiment file (evolve, re-evaluate) for the experiment-file cases.
EXPERIMENT = {
    "name": "tiny",
    "tasks": ["CartPole-v1"],
    "evolve": {
        "units": 10, "n_trials": 2, "n_seeds": 1, "training_steps": 128, "n_envs": 1,
        "popsize": 2, "sampler_seed": 0, "ppo": {"n_steps": 64, "batch_size": 64, "n_epochs": 1},
    },
    "reevaluate": {"top": 1, "seeds": 1},
    "test": {"agents": ["ppo"], "seeds": [10], "training_steps": 128},
    "report": {"dynamics": False, "interactive": False, "html": False},
}  # fmt: skip


# -- running commands ----------------------------------------------------------------------------


@dataclass
class Proc:
    """One command's result."""

    args: list[str]
    rc: int
    out: str
    err: str
    seconds: float
    hang: bool = False


@dataclass
class Case:
    """One fault case: ``run(ctx)`` plants the fault in ``ctx.folder`` and runs the commands."""

    family: str
    name: str
    run: Callable[[Ctx], None]
    needs: tuple[str, ...] = ()
    timeout: float = 120.0


@dataclass
class Ctx:
    """What a case works in and what it found."""

    folder: Path
    seeds: Seeds
    timeout: float
    procs: list[Proc] = field(default_factory=list)
    left: list[str] = field(default_factory=list)
    bricked: list[str] = field(default_factory=list)
    lost: int = 0
    code_run: bool = False
    other: list[str] = field(default_factory=list)

    def env(self, **extra: str) -> dict[str, str]:
        return {**os.environ, "PYTHONUNBUFFERED": "1", "COLUMNS": "200", **extra}

    def cli(
        self,
        *args: str,
        storage: str | None = None,
        timeout: float | None = None,
        env: dict[str, str] | None = None,
        check_files: bool = True,
    ) -> Proc:
        """``python -m ermrl ARGS`` in the case's folder. A failed command's new or changed
        files (the storage ``storage`` names aside) are recorded as files left behind."""
        before = listing(self.folder)
        start = time.monotonic()
        cmd = [sys.executable, "-m", "ermrl", *args]
        try:
            done = subprocess.run(
                cmd, cwd=self.folder, env=env or self.env(), capture_output=True, text=True,
                timeout=timeout or self.timeout, check=False,
            )  # fmt: skip
            proc = Proc(list(args), done.returncode, done.stdout, done.stderr, 0.0)
        except subprocess.TimeoutExpired as err:
            proc = Proc(list(args), -9, _text(err.stdout), _text(err.stderr), 0.0, hang=True)
        proc.seconds = time.monotonic() - start
        self.procs.append(proc)
        if check_files and proc.rc != 0 and proc.rc not in SIGNAL_CODES:
            self.note_left(before, storage, args[0])
        return proc

    def popen(self, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
        return subprocess.Popen(
            [sys.executable, "-m", "ermrl", *args], cwd=self.folder, env=env or self.env(),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip

    def finish(self, proc: subprocess.Popen[str], args: list[str], start: float) -> Proc:
        """Wait for a started command (killed past the timeout: a hang)."""
        try:
            out, err = proc.communicate(timeout=self.timeout)
            result = Proc(args, proc.returncode, out, err, time.monotonic() - start)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            result = Proc(args, -9, out, err, time.monotonic() - start, hang=True)
        self.procs.append(result)
        return result

    def note_left(self, before: dict[str, tuple[int, int]], storage: str | None, what: str) -> None:
        after = listing(self.folder)
        keep = _storage_names(storage)
        changed = [
            p for p, stat in after.items()
            if before.get(p) != stat and not any(p == k or p.startswith(k + ".") for k in keep)
            # a folder that was there: only its mtime moved (its new entries count themselves)
            and not (p in before and (self.folder / p).is_dir())
            and not p.startswith(("s.db", "s.log"))  # the case's storage and its lock files
        ]  # fmt: skip
        self.left += [f"{what}: {p}" for p in sorted(changed)]

    def expect(self, proc: Proc, rc: int | set[int], text: str = "", one_line: bool = True) -> None:
        """The command ended with exit code ``rc`` (and said ``text`` in one line)."""
        codes = {rc} if isinstance(rc, int) else rc
        if proc.hang:
            return
        if proc.rc not in codes:
            self.other.append(f"{proc.args[0]} rc {proc.rc} (expected {sorted(codes)})")
        elif text and text not in proc.err + proc.out:
            self.other.append(f"{proc.args[0]} did not say {text!r}")
        elif one_line and proc.rc != 0 and len(lines := _said(proc.err)) > 1:
            self.other.append(f"{proc.args[0]} said {len(lines)} lines")

    def trials(self, storage: str, study: str = "s") -> dict[int, dict[str, str]] | None:
        """The study's trials by number (``study export``), or ``None`` when it cannot be read
        (the storage is bricked)."""
        proc = self.cli("study", "export", "--storage", storage, "--study-name", study,
                        "--out", "-", storage=storage)  # fmt: skip
        if proc.rc != 0:
            self.bricked.append(f"study export rc {proc.rc}: {_last_line(proc.err)}")
            return None
        rows = csv.DictReader(io.StringIO(proc.out))
        return {int(row["number"]): row for row in rows}

    def check_kept(self, storage: str, before: dict[int, dict[str, str]] | None) -> None:
        """COMPLETE trials of ``before`` are still COMPLETE."""
        after = self.trials(storage)
        if before is None or after is None:
            return
        gone = [n for n, row in before.items() if row["state"] == "COMPLETE"
                and after.get(n, {}).get("state") != "COMPLETE"]  # fmt: skip
        self.lost += len(gone)

    def evolve_again(self, storage: str, n_trials: int = 4, expect_ok: bool = True) -> Proc:
        """The next evolve on the storage; a failure is a bricked storage."""
        proc = self.cli("evolve", *EVOLVE, "--storage", storage, "--n-trials", str(n_trials),
                        storage=storage)  # fmt: skip
        if expect_ok and proc.rc != 0 and not proc.hang:
            self.bricked.append(f"next evolve rc {proc.rc}: {_last_line(proc.err)}")
        return proc


def _said(err: str) -> list[str]:
    """The lines of ``err``, a Python warning (``FILE:LINE: XWarning: ...`` and its indented
    source line; a library's, about the data, not the fault) aside."""
    lines = err.strip().splitlines()
    said = []
    for i, line in enumerate(lines):
        warning = re.match(r"^\S+:\d+: \w*Warning: ", line)
        follows = (
            i > 0 and line.startswith(" ") and re.match(r"^\S+:\d+: \w*Warning: ", lines[i - 1])
        )
        if not warning and not follows:
            said.append(line)
    return said


def _text(value: str | bytes | None) -> str:
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    return value or ""


def _last_line(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[-1][:200] if lines else ""


def _storage_names(storage: str | None) -> list[str]:
    if not storage:
        return []
    path = re.sub(r"^(sqlite|journal):///", "", storage)
    return [str(Path(path))] if "://" not in path else []  # relative to the case's folder


def listing(folder: Path) -> dict[str, tuple[int, int]]:
    """Every path under ``folder`` (relative) with its size and modification time."""
    found = {}
    for path in folder.rglob("*"):
        with contextlib.suppress(OSError):
            stat = path.lstat()
            size = 0 if path.is_dir() else stat.st_size
            found[str(path.relative_to(folder))] = (size, stat.st_mtime_ns)
    return found


# -- shared starting points, made once per pass ---------------------------------------------------


class Seeds:
    """Studies and run folders made once and copied into the cases that start from them."""

    def __init__(self, root: Path, timeout: float) -> None:
        self.root = root
        self.timeout = timeout
        self._made: dict[str, Path] = {}

    def get(self, name: str) -> Path:
        if name not in self._made:
            folder = self.root / f"seed-{name}"
            folder.mkdir()
            getattr(self, f"_make_{name.replace('-', '_')}")(folder)
            self._made[name] = folder
        return self._made[name]

    def copy(self, name: str, into: Path) -> None:
        shutil.copytree(self.get(name), into, dirs_exist_ok=True, symlinks=True)

    def _run(self, folder: Path, *args: str) -> None:
        done = subprocess.run(
            [sys.executable, "-m", "ermrl", *args], cwd=folder, capture_output=True, text=True,
            timeout=600, check=False, env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        if done.returncode != 0:
            raise RuntimeError(f"seed command failed: ermrl {' '.join(args)}\n{done.stderr}")

    def _make_sqlite(self, folder: Path) -> None:
        """Study ``s`` in ``s.db``: 3 COMPLETE trials, CMA-ES state stored."""
        self._run(folder, "evolve", *EVOLVE, "--storage", "sqlite:///s.db", "--n-trials", "3")

    def _make_journal(self, folder: Path) -> None:
        self._run(folder, "evolve", *EVOLVE, "--storage", "s.log", "--n-trials", "3")

    def _make_runs(self, folder: Path) -> None:
        """The SQLite study and its test phase in ``runs/s`` (ppo, res-ppo; models saved)."""
        self.copy("sqlite", folder)
        self._run(folder, "test", "--study-name", "s", "--storage", "sqlite:///s.db",
                  "--agents", "ppo", "res-ppo", "--seeds", "10", "--training-steps", "128",
                  "--out", "runs/s", "--progress", "none")  # fmt: skip

    def _make_experiment(self, folder: Path) -> None:
        """The tiny experiment after its evolve and re-evaluate stages."""
        import yaml

        (folder / "exp.yaml").write_text(yaml.safe_dump(EXPERIMENT, sort_keys=False))
        self._run(folder, "run", "exp.yaml", "--stage", "evolve", "reevaluate", "--quiet")

    def _make_pendulum(self, folder: Path) -> None:
        """A Pendulum-positions study with 4 COMPLETE trials and nothing trained (made in
        process): for the test phase and report cases that need episodes that never end."""
        import optuna

        from ermrl.config import (
            BudgetConfig,
            EncoderConfig,
            EvolveConfig,
            PPOConfig,
            Problem,
            ReservoirSpace,
            SearchConfig,
            TaskConfig,
        )
        from ermrl.search import create_or_resume_study, sample_params

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        space = ReservoirSpace(units=10)
        problem = Problem(
            task=TaskConfig("Pendulum-v1", "positions"),
            encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
            ppo=PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64}),
            budget=BudgetConfig(training_steps=256),
            seeds=(0,),
        )
        config = EvolveConfig(problem=problem, space=space, search=SearchConfig(n_trials=4))
        study = create_or_resume_study(config, f"sqlite:///{folder / 's.db'}", "s",
                                       heartbeat_interval=None)  # fmt: skip
        for value in (-900.0, -800.0, -1000.0, -700.0):
            trial = study.ask()
            sample_params(trial, space)
            study.tell(trial, value)


# -- helpers for planting faults ------------------------------------------------------------------


def sqlite_rows(db: Path, sql: str, args: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    with contextlib.closing(sqlite3.connect(db, timeout=30)) as con, con:
        return con.execute(sql, args).fetchall()


def wait_for(test: Callable[[], bool], proc: subprocess.Popen[str], seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and proc.poll() is None:
        with contextlib.suppress(sqlite3.Error, OSError):
            if test():
                return True
        time.sleep(0.2)
    return False


def n_running(db: Path) -> int:
    uri = f"file:{db}?mode=ro"
    with contextlib.closing(sqlite3.connect(uri, uri=True, timeout=5)) as con:
        return int(con.execute("SELECT COUNT(*) FROM trials WHERE state='RUNNING'").fetchone()[0])


@contextlib.contextmanager
def tmpfs(where: Path, size_kb: int, free_kb: int) -> Iterator[Path]:
    """A tmpfs of ``size_kb`` at ``where`` with only ``free_kb`` left free (a filler file)."""
    where.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(where)],
                   check=True, capture_output=True)  # fmt: skip
    try:
        filler = where / ".filler"
        with contextlib.suppress(OSError), open(filler, "wb") as f:
            f.write(b"\0" * max(0, (size_kb - free_kb) * 1024))
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], check=False, capture_output=True)


def fill_up(where: Path, free_kb: int) -> None:
    """Fill an already mounted tmpfs so that about ``free_kb`` stay free."""
    usage = shutil.disk_usage(where)
    with contextlib.suppress(OSError), open(where / ".filler2", "wb") as f:
        f.write(b"\0" * max(0, usage.free - free_kb * 1024))


class TcpProxy:
    """A TCP proxy to a server, stopped and started on the same port: a server restart
    without touching the real server (others use it)."""

    def __init__(self, port: int) -> None:
        self.target = ("127.0.0.1", port)
        self._sockets: list[socket.socket] = []
        self._lock = threading.Lock()
        probe = socket.socket()
        probe.bind(("127.0.0.1", 0))
        self.port = probe.getsockname()[1]
        probe.close()
        self._listener: socket.socket | None = None
        self.start()

    def start(self) -> None:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(64)
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()

    def stop(self) -> None:
        with self._lock:
            if self._listener is not None:
                with contextlib.suppress(OSError):
                    self._listener.shutdown(socket.SHUT_RDWR)
                self._listener.close()
                self._listener = None
            for sock in self._sockets:
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
            self._sockets.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            try:
                server = socket.create_connection(self.target, timeout=5)
            except OSError:
                client.close()
                continue
            server.settimeout(None)
            with self._lock:
                self._sockets += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(source: socket.socket, sink: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                sink.sendall(data)
        with contextlib.suppress(OSError):
            sink.shutdown(socket.SHUT_WR)


def reachable(address: tuple[str, int]) -> bool:
    with contextlib.suppress(OSError), socket.create_connection(address, timeout=2):
        return True
    return False


def available(need: str) -> bool:
    if need == "root":
        return os.geteuid() == 0 and shutil.which("mount") is not None
    return reachable({"postgresql": POSTGRES, "mysql": MYSQL, "redis": REDIS}[need])


# -- 1. a SQLite hot journal ----------------------------------------------------------------------

HOT_JOURNAL = """
import os, signal, sqlite3, sys
con = sqlite3.connect(sys.argv[1], isolation_level=None)
con.execute("PRAGMA cache_size=2")
con.execute("BEGIN")
con.execute("CREATE TABLE spill (x BLOB)")
for _ in range(400):
    con.execute("INSERT INTO spill VALUES (randomblob(4000))")
con.execute("UPDATE trials SET state = 'FAIL'")
os.kill(os.getpid(), signal.SIGKILL)
"""


def hot_journal(action: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("sqlite", ctx.folder)
        url = "sqlite:///s.db"
        before = ctx.trials(url)
        subprocess.run([sys.executable, "-c", HOT_JOURNAL, "s.db"], cwd=ctx.folder,
                       capture_output=True, check=False)  # fmt: skip
        if not (ctx.folder / "s.db-journal").exists():
            ctx.other.append("setup: no hot journal was left")
            return
        if action == "repair":
            ctx.expect(ctx.cli("study", "repair", "--storage", url, storage=url), 0)
        elif action == "evolve":
            ctx.expect(ctx.evolve_again(url), 0)
        elif action == "show":
            ctx.expect(ctx.cli("study", "show", "--storage", url, "--study-name", "s",
                               storage=url), 0)  # fmt: skip
        ctx.check_kept(url, before)

    return run


# -- 2. interrupting the first generation --------------------------------------------------------


def interrupt(sig: signal.Signals) -> Callable[[Ctx], None]:
    """A signal while the first generation trains; the rerun must train every trial, the
    unevolved reference (trial with sr = lr = input_scaling = 1) included. After kill -9 the
    rerun follows ``study fail-stale --older-than 1s``, as a user would after a crash."""

    def run(ctx: Ctx) -> None:
        url = "sqlite:///s.db"
        args = ["evolve", *EVOLVE, "--storage", url, "--n-trials", "2"]
        args[args.index("128")] = "3000"  # training steps: long enough to be interrupted
        start = time.monotonic()
        proc = ctx.popen(*args)
        if not wait_for(lambda: n_running(ctx.folder / "s.db") > 0, proc, ctx.timeout / 2):
            ctx.other.append("setup: no trial started running")
        time.sleep(1.0)
        proc.send_signal(sig)
        ctx.finish(proc, args, start)
        if sig == signal.SIGKILL:
            # kill -9 leaves the trials RUNNING: the rerun would wait the heartbeat grace period
            # (300 s) for them. A user fails them at once (the shortest age is 1 s), which
            # queues them again.
            time.sleep(1.5)
            fail = ["study", "fail-stale", "--storage", url, "--study-name", "s"]
            ctx.expect(ctx.cli(*fail, "--older-than", "1s", storage=url), 0)
        ctx.expect(ctx.cli(*args, storage=url), 0)
        trials = ctx.trials(url)
        if trials is None:
            return
        reference = [
            row for row in trials.values() if row["state"] == "COMPLETE"
            and all(float(row.get(f"params_{p}") or 0) == 1.0 for p in ("sr", "lr", "input_scaling"))
        ]  # fmt: skip
        if not reference:
            ctx.lost += 1
        if [r for r in trials.values() if r["state"] in ("RUNNING", "WAITING")]:
            ctx.other.append("trials left RUNNING or WAITING after the rerun")

    return run


# -- 3. an env id naming a module, in study data ---------------------------------------------------

EVIL_ID = "fpevil:Evil-v0"
EVIL_MODULE = """
from pathlib import Path
Path(__file__).with_name("CODE_RAN").write_text("imported")
import gymnasium
class Evil(gymnasium.Env):
    pass
"""


def _plant_module(ctx: Ctx) -> dict[str, str]:
    (ctx.folder / "fpevil.py").write_text(EVIL_MODULE)
    return ctx.env(PYTHONPATH=f"{ctx.folder}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")


def _evil_study(ctx: Ctx, seed: str = "sqlite") -> None:
    ctx.seeds.copy(seed, ctx.folder)
    db = ctx.folder / "s.db"
    ((value,),) = sqlite_rows(
        db, "SELECT value_json FROM study_user_attributes WHERE key='ermrl_config'"
    )
    sqlite_rows(db, "UPDATE study_user_attributes SET value_json=? WHERE key='ermrl_config'",
                (value.replace("CartPole-v1", EVIL_ID),))  # fmt: skip


def code_from_data(command: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        env = _plant_module(ctx)
        url = "sqlite:///s.db"
        base = ["--study-name", "s", "--storage", url]
        if command == "import":
            ctx.seeds.copy("sqlite", ctx.folder)
            ctx.cli("study", "export", *base, "--out", "study.json")
            snapshot = ctx.folder / "study.json"
            snapshot.write_text(snapshot.read_text().replace("CartPole-v1", EVIL_ID))
            proc = ctx.cli("study", "import", "--storage", "sqlite:///t.db", "--snapshot",
                           "study.json", env=env)  # fmt: skip
        elif command == "settings":  # a run folder's settings.json: its env_id is never read
            ctx.seeds.copy("runs", ctx.folder)
            settings = ctx.folder / "runs/s/agents/res-ppo/seed_10/settings.json"
            settings.write_text(settings.read_text().replace("CartPole-v1", EVIL_ID))
            proc = ctx.cli("dynamics", "--run", "runs/s", "--agent", "res-ppo", "--seed", "10",
                           "--out", "dyn", env=env)  # fmt: skip
        else:
            _evil_study(ctx)
            extra = {
                "test": ["--agents", "ppo", "--seeds", "10", "--training-steps", "128"],
                "test-ppo-full": ["--agents", "ppo-full", "--seeds", "10",
                                  "--training-steps", "128"],
                "evolve": [],
                "report": ["--no-interactive", "--no-html", "--no-dynamics"],
            }[command]  # fmt: skip
            if command == "evolve":
                proc = ctx.cli("evolve", *EVOLVE, "--storage", url, "--n-trials", "4",
                               env=env, storage=url)  # fmt: skip
            else:
                name = command.split("-")[0]
                proc = ctx.cli(name, *base, "--out", "out", *extra, env=env, storage=url)
        ctx.code_run = (ctx.folder / "CODE_RAN").exists()
        if command == "settings":  # the replay takes the task from config.yaml (checked)
            ctx.expect(proc, {0, 2})
        elif command != "report":  # a report only shows the id; it runs nothing from it
            ctx.expect(proc, 2)

    return run


# -- 4. journal repair ---------------------------------------------------------------------------


def _glue(text: str) -> str:
    """``sed '/"op_code":4/{N;s/\\n//}'``: each line with op_code 4 glued to the next one."""
    lines, out, i = text.split("\n"), [], 0
    while i < len(lines):
        if '"op_code":4' in lines[i].replace(" ", "") and i + 1 < len(lines):
            out.append(lines[i] + lines[i + 1])
            i += 2
        else:
            out.append(lines[i])
            i += 1
    return "\n".join(out)


def journal_damage(kind: str, by: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("journal", ctx.folder)
        before = ctx.trials("s.log")
        log = ctx.folder / "s.log"
        text = log.read_text()
        lines = text.rstrip("\n").split("\n")
        if kind == "glued":
            if _glue(text) == text:
                ctx.other.append("setup: no record to glue")
            log.write_text(_glue(text))
        elif kind == "torn-tail":
            log.write_text(text + lines[-1][: len(lines[-1]) // 2])
        elif kind == "garbage-line":
            middle = len(lines) // 2
            log.write_text(
                "\n".join([*lines[:middle], '{"op_code": 4, "wor', *lines[middle:]]) + "\n"
            )
        elif kind == "nul-tail":
            log.write_bytes(text.encode() + b"\0" * 4096)
        if by == "repair":
            ctx.expect(ctx.cli("study", "repair", "--storage", "s.log", storage="s.log"), 0)
        else:
            ctx.expect(ctx.evolve_again("s.log"), 0)
        ctx.check_kept("s.log", before)

    return run


# -- 5. dangling and stale locks --------------------------------------------------------------------


def dangling_lock(lock: str, command: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        journal = lock.startswith("s.log")
        ctx.seeds.copy("journal" if journal else "sqlite", ctx.folder)
        url = "s.log" if journal else "sqlite:///s.db"
        before = ctx.trials(url)
        path = ctx.folder / lock
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        if command == "stale":  # a lock link to a real file, last touched 10 minutes ago
            os.symlink(ctx.folder / "gone-owner", path)
            old = time.time() - 600
            os.utime(path, (old, old), follow_symlinks=False)
        else:
            os.symlink("/nonexistent", path)
        if command == "repair":
            ctx.expect(ctx.cli("study", "repair", "--storage", url, storage=url), 0)
        elif command == "show":
            ctx.expect(ctx.cli("study", "show", "--storage", url, "--study-name", "s",
                               storage=url), 0)  # fmt: skip
        else:
            ctx.expect(ctx.evolve_again(url), 0)
        ctx.check_kept(url, before)

    return run


# -- 6. a malformed CMA-ES state ---------------------------------------------------------------------


def _cma_edit(db: Path, edit: Callable[[dict[str, Any]], str]) -> bool:
    from ermrl.search._samplers import _join_chunks

    rows = sqlite_rows(db, "SELECT trial_id, key, value_json FROM trial_system_attributes "
                       "WHERE key LIKE 'cma:state:%'")  # fmt: skip
    if not rows:
        return False
    holder = max(r[0] for r in rows)
    chunks = {k: json.loads(v) for t, k, v in rows if t == holder}
    text = edit(json.loads(_join_chunks(chunks, "cma:state:")))
    sqlite_rows(db, "DELETE FROM trial_system_attributes WHERE trial_id=? AND key LIKE "
                "'cma:state:%'", (holder,))  # fmt: skip
    for i, j in enumerate(range(0, len(text), 2045)):
        sqlite_rows(
            db,
            "INSERT INTO trial_system_attributes (trial_id, key, value_json) VALUES (?, ?, ?)",
            (holder, f"cma:state:{i}", json.dumps(text[j : j + 2045])),
        )
    return True


def _attrs(**attrs: Any) -> Callable[[dict[str, Any]], str]:
    def edit(state: dict[str, Any]) -> str:
        state["attrs"].update(attrs)
        return json.dumps(state)

    return edit


def _array(values: Any) -> Any:
    import numpy as np

    from ermrl.search._samplers import _encode

    return _encode(np.asarray(values, dtype=float))


_DEEP = 50_000
CMA_STATES: dict[str, Callable[[], Callable[[dict[str, Any]], str]]] = {
    "popsize-0": lambda: _attrs(_popsize=0),
    "nan-mean": lambda: _attrs(_mean=_array([float("nan")] * 3)),
    "mean-wrong-length": lambda: _attrs(_mean=_array([0.5] * 5)),
    "covariance-wrong-shape": lambda: _attrs(_C=_array([[1.0, 0.0], [0.0, 1.0]])),
    "string-sigma": lambda: _attrs(_sigma="big"),
    "nested-50k": lambda: (
        lambda state: (
            '{"__cmaes__": "CMA", "attrs": {"_x": ' + '{"__list__": [' * _DEEP + "]}" * _DEEP + "}}"
        )
    ),
    "not-json": lambda: lambda state: '{"__cmaes__": "CMA", "attrs": {',
}


def cma_state(kind: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("sqlite", ctx.folder)
        url = "sqlite:///s.db"
        before = ctx.trials(url)
        if not _cma_edit(ctx.folder / "s.db", CMA_STATES[kind]()):
            ctx.other.append("setup: no CMA-ES state stored")
            return
        ctx.expect(ctx.evolve_again(url, 4), 0, one_line=False)  # the resume reads the state
        trials = ctx.trials(url)
        if trials and [r for r in trials.values() if r["state"] == "RUNNING"]:
            ctx.other.append("trials left RUNNING")
        ctx.check_kept(url, before)

    return run


# -- 7. a short storage outage ----------------------------------------------------------------------


@contextlib.contextmanager
def server_database(kind: str) -> Iterator[str]:
    """A fresh database (PostgreSQL, MySQL) or key prefix (Redis), removed afterwards."""
    name = f"ermrl_fault_{uuid.uuid4().hex[:10]}"
    if kind == "redis":
        import redis

        client = redis.Redis(host=REDIS[0], port=REDIS[1])
        try:
            yield f"redis://{REDIS[0]}:{REDIS[1]}/0?prefix={name}"
        finally:
            for key in client.scan_iter(f"{name}:*"):
                client.delete(key)
            client.close()
        return
    if kind == "postgresql":
        import psycopg2

        admin: Any = psycopg2.connect(f"postgresql://postgres@{POSTGRES[0]}:{POSTGRES[1]}/test")
        admin.autocommit = True
        url, drop = (f"postgresql://postgres@{POSTGRES[0]}:{POSTGRES[1]}/{name}",
                     f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")  # fmt: skip
    else:
        import pymysql

        admin = pymysql.connect(host=MYSQL[0], port=MYSQL[1], user="root", password="",
                                autocommit=True)  # fmt: skip
        url, drop = f"mysql+pymysql://root@{MYSQL[0]}:{MYSQL[1]}/{name}", f"DROP DATABASE {name}"
    with admin.cursor() as cur:
        cur.execute(f"CREATE DATABASE {name}")
    try:
        yield url
    finally:
        with admin.cursor() as cur:
            cur.execute(drop)
        admin.close()


def _n_running_server(kind: str, url: str) -> int:
    """RUNNING trials in a PostgreSQL or MySQL storage (0 while its tables do not exist)."""
    sql = "SELECT COUNT(*) FROM trials WHERE state = 'RUNNING'"
    try:
        if kind == "postgresql":
            import psycopg2

            con: Any = psycopg2.connect(url, connect_timeout=5)
        else:
            import pymysql

            name = url.rsplit("/", 1)[1]
            con = pymysql.connect(host=MYSQL[0], port=MYSQL[1], user="root", password="",
                                  database=name, connect_timeout=5)  # fmt: skip
        with contextlib.closing(con), con.cursor() as cur:
            cur.execute(sql)
            return int(cur.fetchone()[0])
    except Exception:  # not created yet
        return 0


def outage(kind: str, seconds: float, workers: int = 2) -> Callable[[Ctx], None]:
    """``workers`` evolve workers on one study while the server is unreachable for
    ``seconds`` (a proxy stopped; Redis paused): every worker finishes, every trial completes."""

    def run(ctx: Ctx) -> None:
        with server_database(kind) as direct:
            proxy = None if kind == "redis" else TcpProxy(POSTGRES[1] if kind == "postgresql"
                                                          else MYSQL[1])  # fmt: skip
            url = direct if proxy is None else direct.replace(f":{proxy.target[1]}/",
                                                              f":{proxy.port}/")  # fmt: skip
            n_trials = 2 * workers
            args = ["evolve", *EVOLVE, "--storage", url, "--n-trials", str(n_trials)]
            args[args.index("128")] = "2000"
            first = ctx.cli("study", "create", "--storage", url, *args[1:-2], storage=url)
            if first.rc != 0:  # an older CLI without `study create` options: let workers make it
                ctx.procs.pop()
            start = time.monotonic()
            procs = [ctx.popen(*args) for _ in range(workers)]
            # Opening a storage is not retried (a wrong URL fails at once), so the outage starts
            # once the workers train: each holds a RUNNING trial (a loaded machine takes more
            # than 8 s to start them).
            if proxy is not None:
                wait_for(lambda: _n_running_server(kind, direct) >= workers, procs[0], 120)
            time.sleep(8 if proxy is None else 1)
            if proxy is not None:
                proxy.stop()
                time.sleep(seconds)
                proxy.start()
            else:
                import redis

                client = redis.Redis(host=REDIS[0], port=REDIS[1])
                client.execute_command("CLIENT", "PAUSE", int(min(seconds, 5) * 1000), "ALL")
                client.close()
            for proc in procs:
                ctx.expect(ctx.finish(proc, args, start), 0)
            trials = ctx.trials(url)
            if trials is not None:
                done = sum(r["state"] == "COMPLETE" for r in trials.values())
                if done < n_trials:
                    ctx.other.append(f"{done}/{n_trials} trials COMPLETE after the outage")
            if proxy is not None:
                proxy.stop()

    return run


# -- 8. servers that never answer ---------------------------------------------------------------


def silent_server(scheme: str, port_of: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        listener = socket.socket()
        listener.bind(("127.0.0.1", 0))
        listener.listen(16)
        port = {"silent": listener.getsockname()[1], "postgresql": POSTGRES[1]}[port_of]
        try:
            url = f"{scheme}://root@127.0.0.1:{port}/test"
            if scheme == "redis":
                url = f"redis://127.0.0.1:{port}/0"
            proc = ctx.cli("study", "show", "--storage", url, "--study-name", "s")
            ctx.expect(proc, 2)
            if proc.seconds > 20 and not proc.hang:
                ctx.other.append(f"took {proc.seconds:.0f} s to fail")
        finally:
            listener.close()

    return run


# -- 9 and 12. a full disk ------------------------------------------------------------------------


def video_full_disk(gif: bool, free_kb: int) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("runs", ctx.folder)
        with tmpfs(ctx.folder / "disk", 256, free_kb) as disk:
            before = set(os.listdir(disk))
            args = ["video", "--run", "runs/s", "--agent", "ppo", "--seed", "10", "--out",
                    str(disk / "v"), "--gif" if gif else "--no-gif", "--quiet"]  # fmt: skip
            proc = ctx.cli(*args)
            left = sorted(set(os.listdir(disk)) - before)
            if proc.rc == 0:
                if "wrote" in proc.out + proc.err and free_kb < 8:
                    ctx.other.append("said it wrote a video on a full disk")
            elif left:
                ctx.left += [f"video: disk/{p}" for p in left]
            elif proc.rc == 3:
                ctx.other.append("no OpenGL/pygame renderer here (rc 3): the case did not run")

    return run


def storage_full_disk(kind: str) -> Callable[[Ctx], None]:
    """The disk fills up while ``evolve`` writes the study; after space is freed the study
    opens and the next evolve runs."""

    def run(ctx: Ctx) -> None:
        disk = ctx.folder / "disk"
        seed = "sqlite" if kind == "sqlite" else "journal"
        ctx.seeds.copy(seed, ctx.folder / "stage")
        with tmpfs(disk, 2048, 2048):
            for p in (ctx.folder / "stage").iterdir():
                (shutil.copytree if p.is_dir() else shutil.copy2)(p, disk / p.name)
            url = "sqlite:///disk/s.db" if kind == "sqlite" else "disk/s.log"
            before = ctx.trials(url)
            fill_up(disk, 24)
            proc = ctx.cli("evolve", *EVOLVE, "--storage", url, "--n-trials", "9", storage=url)
            if proc.rc == 0:
                ctx.other.append("evolve succeeded on a full disk (the disk was not full enough)")
            for filler in disk.glob(".filler*"):
                filler.unlink()
            time.sleep(1.5)  # the shortest age fail-stale takes is 1 s
            ctx.cli("study", "fail-stale", "--storage", url, "--study-name", "s",
                    "--older-than", "1s", storage=url)  # fmt: skip
            ctx.evolve_again(url, n_trials=10)
            ctx.check_kept(url, before)

    return run


# -- 10. a damaged sb3 checkpoint -------------------------------------------------------------------


def sb3_checkpoint(kind: str) -> Callable[[Ctx], None]:
    """A test-phase run killed after its first checkpoint, whose checkpoint is then damaged:
    the rerun sets it aside in one line and trains from the start."""

    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("sqlite", ctx.folder)
        args = ["test", "--study-name", "s", "--storage", "sqlite:///s.db", "--agents", "ppo",
                "--seeds", "10", "--training-steps", "6000", "--backend", "sb3",
                "--checkpoint-every", "256", "--out", "runs", "--progress", "none"]  # fmt: skip
        folder = ctx.folder / "runs/agents/ppo/seed_10/checkpoints"
        start = time.monotonic()
        proc = ctx.popen(*args)
        if not wait_for(lambda: bool(list(folder.glob("model-*.zip"))), proc, ctx.timeout / 2):
            ctx.other.append("setup: no checkpoint was written")
        time.sleep(0.5)
        proc.kill()
        ctx.finish(proc, args, start)
        models = sorted(folder.glob("model-*.zip"))
        if kind == "truncated" and models:
            data = models[-1].read_bytes()
            models[-1].write_bytes(data[: len(data) // 2])
        elif kind == "garbage" and models:
            models[-1].write_bytes(b"\0garbage" * 100)
        elif kind == "state-garbage":
            (folder / "state.json").write_bytes(b"\xff{not json")
        proc2 = ctx.cli(*args, timeout=180)  # the same command again
        ctx.expect(proc2, 0, one_line=False)

    return run


# -- 11. experiment files ------------------------------------------------------------------------------

BAD_FILES: dict[str, bytes | str] = {
    "latin-1": b"name: tiny\ndescription: caf\xe9\ntasks: [CartPole-v1]\n",
    "dev-zero": "/dev/zero",
    "out-mapping": b"name: tiny\nout: {a: 1}\ntasks: [CartPole-v1]\n",
    "publish-int": b"name: tiny\npublish: 5\ntasks: [CartPole-v1]\n",
    "storage-list": b"name: tiny\nstorage: [x]\ntasks: [CartPole-v1]\n",
    "duplicate-key": b"name: tiny\nname: other\ntasks: [CartPole-v1]\n",
    "nested-duplicate": b"name: tiny\ntasks: [CartPole-v1]\nevolve: {units: 10, units: 20}\n",
    "huge": b"name: tiny\n" + b"#" * (1 << 20) + b"\n",
    "python-tag": b"name: !!python/object/apply:os.system ['touch CODE_RAN']\n",
    "alias-bomb": b"a: &a [x, x, x, x, x, x, x, x, x]\n"
    + b"".join(
        b"%c: &%c [*%c, *%c, *%c, *%c, *%c, *%c, *%c, *%c, *%c]\n" % ((98 + i,) * 2 + (97 + i,) * 9)
        for i in range(8)
    ),  # fmt: skip
}


def experiment_file(kind: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        content = BAD_FILES[kind]
        path = content if isinstance(content, str) else "exp.yaml"
        if isinstance(content, bytes):
            (ctx.folder / "exp.yaml").write_bytes(content)
        proc = ctx.cli("run", path, "--stage", "evolve", "--quiet")
        ctx.expect(proc, 2)
        ctx.code_run = (ctx.folder / "CODE_RAN").exists()

    return run


CHANGES: dict[str, Callable[[dict[str, Any]], None]] = {
    "popsize": lambda d: d["evolve"].update(popsize=3),
    "sampler-seed": lambda d: d["evolve"].update(sampler_seed=5),
    "reevaluate-top": lambda d: d["reevaluate"].update(top=2),
    "reevaluate-steps": lambda d: d["reevaluate"].update(steps=256),
    "reevaluate-seeds": lambda d: d["reevaluate"].update(seeds=2),
}


def experiment_change(kind: str) -> Callable[[Ctx], None]:
    """A setting changed in the file after its study or re-evaluation ran: refused in one
    line, and the resolved file is left as it was."""

    def run(ctx: Ctx) -> None:
        import copy

        import yaml

        ctx.seeds.copy("experiment", ctx.folder)
        doc = copy.deepcopy(EXPERIMENT)
        CHANGES[kind](doc)
        (ctx.folder / "exp.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        stages = ["evolve"] if kind in ("popsize", "sampler-seed") else ["reevaluate"]
        proc = ctx.cli("run", "exp.yaml", "--stage", *stages, "--quiet", storage="ermrl.db")
        ctx.expect(proc, 2)

    return run


# -- 12. smaller failures -----------------------------------------------------------------------------


def crafted_policy(kind: str, command: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        import pickle

        import torch

        ctx.seeds.copy("runs", ctx.folder)
        path = ctx.folder / "runs/s/agents/res-ppo/seed_10/policy.pt"
        if kind == "garbage":
            path.write_bytes(b"\0garbage" * 64)
        elif kind == "empty":
            path.write_bytes(b"")
        elif kind == "pickle":
            path.write_bytes(pickle.dumps({"weight": [1, 2, 3]}))
        elif kind in ("torch-pickle", "not-a-state-dict", "wrong-shapes"):
            payload: Any = {
                "torch-pickle": {"weight": Planted()},
                "not-a-state-dict": [torch.zeros(3)],
                "wrong-shapes": {k: torch.zeros(1) for k in torch.load(path, weights_only=True)},
            }[kind]  # fmt: skip
            torch.save(payload, path)
        if command == "dynamics":
            proc = ctx.cli("dynamics", "--run", "runs/s", "--agent", "res-ppo", "--seed", "10",
                           "--out", "dyn", "--quiet")  # fmt: skip
            ctx.expect(proc, 2)
        else:
            proc = ctx.cli("report", "--study-name", "s", "--storage", "sqlite:///s.db",
                           "--runs", "runs/s", "--out", "report", "--no-interactive",
                           "--no-html", "--quiet", storage="sqlite:///s.db")  # fmt: skip
            ctx.expect(proc, {0, 2})

    return run


class Planted:
    """A class a pickle names (a torch pickle of it must not load)."""


def oversized_record(name: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("runs", ctx.folder)
        path = ctx.folder / "runs/s/agents/ppo/seed_10" / name
        path.unlink()
        path.symlink_to("/dev/zero")
        proc = ctx.cli("report", "--study-name", "s", "--storage", "sqlite:///s.db",
                       "--runs", "runs/s", "--out", "report", "--no-interactive", "--no-html",
                       "--no-dynamics", "--quiet", storage="sqlite:///s.db", timeout=120)  # fmt: skip
        ctx.expect(proc, {0, 2})

    return run


def broken_pipe(command: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("sqlite", ctx.folder)
        args = {"show": ["study", "show"], "export": ["study", "export", "--out", "-"],
                "list": ["study", "list"]}[command]  # fmt: skip
        start = time.monotonic()
        proc = ctx.popen(*args, "--storage", "sqlite:///s.db",
                         *(["--study-name", "s"] if command != "list" else []))  # fmt: skip
        assert proc.stdout is not None
        proc.stdout.close()  # the reader is gone before the first line
        result = ctx.finish(proc, args, start)
        ctx.expect(result, {0, 141})

    return run


def report_interrupted(ctx: Ctx) -> None:
    """Ctrl-C while the report is staged, then the rerun: no hidden staging folder left."""
    ctx.seeds.copy("runs", ctx.folder)
    args = ["report", "--study-name", "s", "--storage", "sqlite:///s.db", "--runs", "runs/s",
            "--out", "report", "--no-interactive", "--no-html", "--no-dynamics"]  # fmt: skip
    start = time.monotonic()
    proc = ctx.popen(*args)
    staged = lambda: any(p.name.startswith(".report.") for p in ctx.folder.iterdir())  # noqa: E731
    if not wait_for(staged, proc, ctx.timeout / 2):
        ctx.other.append("setup: the report finished before it could be interrupted")
    proc.send_signal(signal.SIGINT)
    ctx.finish(proc, args, start)
    ctx.expect(ctx.cli(*args, storage="sqlite:///s.db"), 0)
    hidden = [p.name for p in ctx.folder.iterdir() if p.name.startswith(".report")]
    ctx.left += [f"report (interrupted): {name}" for name in hidden]


def sigterm(command: str) -> Callable[[Ctx], None]:
    """SIGTERM while ``test`` trains or ``report`` writes: exit 143 with one line."""

    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("pendulum", ctx.folder)
        args = {
            "report": ["report", "--no-interactive", "--no-html", "--no-dynamics"],
            "test": ["test", "--agents", "ppo", "--seeds", "1", "--training-steps", "200000"],
        }[command] + ["--study-name", "s", "--storage", "sqlite:///s.db", "--out", "out"]
        started = (
            (lambda: any(p.name.startswith(".out.") for p in ctx.folder.iterdir()))
            if command == "report" else (lambda: (ctx.folder / "out/config.yaml").exists())
        )  # fmt: skip
        start = time.monotonic()
        proc = ctx.popen(*args)
        if not wait_for(started, proc, ctx.timeout / 2):
            ctx.other.append("setup: the command ended before the signal")
        proc.send_signal(signal.SIGTERM)
        result = ctx.finish(proc, args, start)
        ctx.expect(result, 143, "SIGTERM")
        hidden = [p.name for p in ctx.folder.iterdir() if p.name.startswith(".")]
        ctx.left += [f"{command} (SIGTERM): {name}" for name in hidden]

    return run


MEMORY_URLS = [
    "sqlite:///%253Amemory%253A",
    "sqlite:///file:x.db?uri=true&mode=memor%2579",
    "sqlite:///file:x.db?uri=true&vfs=%256Demdb",
    "sqlite:///file:x.db?mode%253Dmemory&uri=true",
    "sqlite:///file:%3A?uri=true",
    "sqlite:///my%20study.db",
    "sqlite:///:memory:",
    "sqlite://",
]


def memory_url(url: str) -> Callable[[Ctx], None]:
    def run(ctx: Ctx) -> None:
        proc = ctx.cli("evolve", *EVOLVE, "--storage", url, "--n-trials", "1")
        ctx.expect(proc, 2)
        if proc.rc == 0:  # accepted: whatever it wrote is on disk under some name
            ctx.other.append(f"accepted; wrote {sorted(os.listdir(ctx.folder))}")

    return run


def failed_test_phase(ctx: Ctx) -> None:
    """A test phase that fails before any run finishes (no Pendulum episode ends in 64
    steps): one line, and no skeleton folder."""
    ctx.seeds.copy("pendulum", ctx.folder)
    proc = ctx.cli("test", "--study-name", "s", "--storage", "sqlite:///s.db", "--agents", "ppo",
                   "--seeds", "1", "--training-steps", "64", "--progress", "none",
                   storage="sqlite:///s.db")  # fmt: skip
    ctx.expect(proc, 2)


def failed_run_stage_test(ctx: Ctx) -> None:
    import yaml

    (ctx.folder / "exp.yaml").write_text(yaml.safe_dump(EXPERIMENT, sort_keys=False))
    proc = ctx.cli("run", "exp.yaml", "--stage", "test", "--quiet")
    if proc.rc == 0:
        ctx.other.append("run --stage test before any evolution succeeded")


# -- the case table --------------------------------------------------------------------------------


# -- 13-19. round four: study names, deep YAML, snapshot edits, symlink loops, publish, Python --


ESCAPING = "../../x/ü y"
TERMINAL = "a\nb\x1b[31mred"


def study_name(kind: str) -> Callable[[Ctx], None]:
    """A study name that leads out of runs/ or holds terminal escapes: refused at creation and
    import; a study Optuna itself named so is listed escaped, and no folder is built from it."""

    def run(ctx: Ctx) -> None:
        name = ESCAPING if kind.startswith("escaping") else TERMINAL
        if kind.endswith("-evolve"):
            unnamed = EVOLVE[: EVOLVE.index("--study-name")] + EVOLVE[EVOLVE.index("--progress") :]
            proc = ctx.cli("evolve", *unnamed, "--storage", "sqlite:///s.db", "--study-name",
                           name, "--n-trials", "1")  # fmt: skip
            ctx.expect(proc, 2, "study name")
            if (ctx.folder / "s.db").exists():
                ctx.other.append("evolve created the storage of a refused name")
            return
        import optuna

        ctx.seeds.copy("runs", ctx.folder)
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        url = f"sqlite:///{ctx.folder / 's.db'}"
        optuna.copy_study(from_study_name="s", from_storage=url, to_storage=url,
                          to_study_name=name)  # fmt: skip
        listed = ctx.cli("study", "list", "--storage", "sqlite:///s.db")
        ctx.expect(listed, 0)
        if "\x1b" in listed.out + listed.err:
            ctx.other.append("study list printed a terminal escape raw")
        work = ctx.folder / "a" / "b"
        work.mkdir(parents=True)
        before = listing(ctx.folder)
        for command in ("test", "report"):
            extra = ["--training-steps", "128", "--seeds", "20"] if command == "test" else []
            done = subprocess.run(
                [sys.executable, "-m", "ermrl", command, "--storage", url,
                 "--study-name", name, *extra], cwd=work, env=ctx.env(), capture_output=True,
                text=True, timeout=ctx.timeout, check=False,
            )  # fmt: skip
            proc = Proc([command], done.returncode, done.stdout, done.stderr, 0.0)
            ctx.procs.append(proc)
            ctx.expect(proc, 2, "--out")
        after = listing(ctx.folder)
        ctx.left += [f"test/report: {p}" for p in after if p not in before and p != "a/b"]

    return run


DEEP = "a: " + "[" * 600 + "]" * 600 + "\n"


def deep_yaml(command: str) -> Callable[[Ctx], None]:
    """YAML nested 600 deep, wherever ermrl reads YAML: one line, exit 2."""

    def run(ctx: Ctx) -> None:
        (ctx.folder / "d.yaml").write_text(DEEP)
        base = ["--storage", "sqlite:///s.db", "--n-trials", "1"]
        args = {
            "run": ["run", "d.yaml", "--dry-run"],
            "hyperparams": ["evolve", *EVOLVE, *base, "--hyperparams", "d.yaml"],
            "ppo": ["evolve", *EVOLVE[: EVOLVE.index("--ppo")], *base,
                    "--ppo", "policy_kwargs=" + "[" * 600 + "]" * 600],
            "suites-file": ["evolve-generalization", "--suites-file", "d.yaml", "--suite", "x",
                            *base],
        }[command]  # fmt: skip
        ctx.expect(ctx.cli(*args, storage="sqlite:///s.db"), 2)

    return run


def snapshot_edit(kind: str) -> Callable[[Ctx], None]:
    """A hand-edited snapshot that would import a study ermrl misreads: refused in one line."""

    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("sqlite", ctx.folder)
        proc = ctx.cli("study", "export", "--storage", "sqlite:///s.db", "--study-name", "s",
                       "--out", "s.json")  # fmt: skip
        doc = json.loads((ctx.folder / "s.json").read_text())
        if kind == "minimize":
            doc["directions"] = ["MINIMIZE"]
        elif kind == "infinity":
            done = [t for t in doc["trials"] if t.get("values")]
            done[0]["values"] = [float("inf")]
        else:
            doc["study_name"] = "x" * 3000
        (ctx.folder / "s.json").write_text(json.dumps(doc))
        proc = ctx.cli("study", "import", "--storage", "sqlite:///t.db", "--snapshot", "s.json",
                       storage="sqlite:///t.db")  # fmt: skip
        ctx.expect(proc, 2)
        if (ctx.folder / "t.db").exists() and sqlite_rows(ctx.folder / "t.db",
                                                          "SELECT COUNT(*) FROM studies")[0][0]:
            ctx.other.append("the edited snapshot was imported")  # fmt: skip

    return run


def symlink_loop(command: str) -> Callable[[Ctx], None]:
    """An output folder that is a symbolic link to itself: one line, exit 2."""

    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("runs", ctx.folder)
        (ctx.folder / "loop").symlink_to("loop")
        common = ["--storage", "sqlite:///s.db", "--study-name", "s"]
        args = {
            "test": ["test", *common, "--training-steps", "128", "--seeds", "20", "--out", "loop"],
            "report": ["report", *common, "--runs", "runs/s", "--out", "loop", "--no-dynamics"],
            "export": ["study", "export", *common, "--out", "loop"],
        }[command]
        ctx.expect(ctx.cli(*args, storage="sqlite:///s.db"), 2)

    return run


def publish_fault(kind: str) -> Callable[[Ctx], None]:
    """The experiment's publish folder is read-only or full: one line, the experiment goes on,
    no partial file under a final name, and a rerun publishes once the folder is writable."""

    def run(ctx: Ctx) -> None:
        import yaml

        ctx.seeds.copy("experiment", ctx.folder)
        doc = {**EXPERIMENT, "publish": "pub"}
        (ctx.folder / "exp.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        pub = ctx.folder / "pub"
        free = 0 if kind == "full" else 64
        with tmpfs(pub, 256, free):
            if kind == "read-only":
                subprocess.run(["mount", "-o", "remount,ro", str(pub)], check=True)
            proc = ctx.cli("run", "exp.yaml", "--quiet", storage="ermrl.db", check_files=False)
            ctx.expect(proc, 0, one_line=False)
            if not (ctx.folder / "runs/tiny/CartPole-v1/test/summary.csv").is_file():
                ctx.other.append("the test stage did not run after the failed publish")
            for path in pub.rglob("*"):
                if path.is_file() and path.name.endswith((".png", ".csv", ".json")):
                    try:
                        if path.suffix == ".json":
                            json.loads(path.read_text())
                        elif path.suffix == ".png" and not path.read_bytes().endswith(
                            b"IEND\xaeB`\x82"):
                            ctx.other.append(f"partial {path.relative_to(pub)}")
                    except (ValueError, OSError):
                        ctx.other.append(f"partial {path.relative_to(pub)}")
        proc = ctx.cli("run", "exp.yaml", "--quiet", storage="ermrl.db")  # pub is a folder now
        ctx.expect(proc, 0, one_line=False)
        if not any(pub.rglob("summary.csv")):
            ctx.other.append("the rerun did not publish")

    return run


PY_CALLS = {
    "test-seeds-string": "ermrl.test('s', URL, seeds='10')",
    "test-misspelled": "ermrl.test('s', URL, training_step=100)",
    "test-options-dict": "ermrl.test('s', URL, options={})",
    "test-storage-number": "ermrl.test('s', 5)",
    "evolve-number": "ermrl.evolve(42, URL)",
    "evolve-storage-none": "ermrl.evolve('CartPole-v1', storage=None)",
    "evolve-misspelled": "ermrl.evolve('CartPole-v1', URL, n_trails=3)",
    "evolve-escaping-name": f"ermrl.evolve('CartPole-v1', URL, {ESCAPING!r})",
    "experiment-number": "ermrl.Experiment.load(5)",
    "report-out-file": "ermrl.report('s', URL, out='s.db')",
    "report-runs-missing": "ermrl.report('s', URL, runs='runs/nosuch')",
    "report-band": "ermrl.report('s', URL, band='ci9')",
}


def python_call(kind: str) -> Callable[[Ctx], None]:
    """A bad call of the Python API: a one-line ermrl.ConfigError, never an internal error."""

    def run(ctx: Ctx) -> None:
        ctx.seeds.copy("sqlite", ctx.folder)
        code = (
            "import sys, ermrl\nURL = 'sqlite:///s.db'\ntry:\n    "
            + PY_CALLS[kind]
            + "\nexcept ermrl.ConfigError as err:\n    print(err, file=sys.stderr)\n"
            "    raise SystemExit(2 if len(str(err).splitlines()) == 1 else 3)\n"
        )
        before = listing(ctx.folder)
        done = subprocess.run([sys.executable, "-c", code], cwd=ctx.folder, env=ctx.env(),
                              capture_output=True, text=True, timeout=ctx.timeout, check=False)  # fmt: skip
        proc = Proc([f"python:{kind}"], done.returncode, done.stdout, done.stderr, 0.0)
        ctx.procs.append(proc)
        ctx.expect(proc, 2)
        ctx.note_left(before, "sqlite:///s.db", proc.args[0])

    return run


def cases() -> list[Case]:
    table = [
        *(Case("1-hot-journal", a, hot_journal(a)) for a in ("show", "evolve", "repair")),
        *(Case("2-interrupt", s.name, interrupt(s), timeout=180)
          for s in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)),
        *(Case("3-code-from-data", c, code_from_data(c))
          for c in ("test", "test-ppo-full", "import", "evolve", "report", "settings")),
        *(Case("4-journal-repair", f"{k}-{by}", journal_damage(k, by))
          for k in ("glued", "torn-tail", "garbage-line", "nul-tail") for by in ("repair", "evolve")
          if by == "repair" or k == "glued"),
        Case("5-lock", "optuna-dangling-evolve", dangling_lock("s.log.lock", "evolve")),
        Case("5-lock", "optuna-dangling-repair", dangling_lock("s.log.lock", "repair")),
        Case("5-lock", "optuna-stale-evolve", dangling_lock("s.log.lock", "stale")),
        Case("5-lock", "ermrl-dangling-evolve", dangling_lock("s.log.ermrl.lock", "evolve")),
        Case("5-lock", "sqlite-dangling-show", dangling_lock("s.db.lock", "show")),
        *(Case("6-cma-state", k, cma_state(k)) for k in CMA_STATES),
        Case("7-outage", "postgresql-25s", outage("postgresql", 25), ("postgresql",), 240),
        Case("7-outage", "mysql-25s", outage("mysql", 25), ("mysql",), 240),
        Case("7-outage", "redis-pause-5s", outage("redis", 5), ("redis",), 240),
        Case("8-silent-server", "mysql-silent", silent_server("mysql", "silent"), timeout=40),
        Case("8-silent-server", "mysql+pymysql-silent", silent_server("mysql+pymysql", "silent"),
             timeout=40),
        Case("8-silent-server", "postgresql-silent", silent_server("postgresql", "silent"),
             timeout=40),
        Case("8-silent-server", "redis-silent", silent_server("redis", "silent"), timeout=200),
        Case("8-silent-server", "mysql-on-postgresql-port", silent_server("mysql", "postgresql"),
             ("postgresql",), 40),
        Case("9-video-full-disk", "mp4-no-space", video_full_disk(False, 0), ("root",)),
        Case("9-video-full-disk", "mp4-16k", video_full_disk(False, 16), ("root",)),
        Case("9-video-full-disk", "gif-16k", video_full_disk(True, 16), ("root",)),
        *(Case("10-sb3-checkpoint", k, sb3_checkpoint(k), timeout=240)
          for k in ("truncated", "garbage", "state-garbage")),
        *(Case("11-experiment-file", k, experiment_file(k)) for k in BAD_FILES),
        *(Case("11-experiment-change", k, experiment_change(k)) for k in CHANGES),
        Case("12-full-disk", "sqlite-evolve", storage_full_disk("sqlite"), ("root",), 180),
        Case("12-full-disk", "journal-evolve", storage_full_disk("journal"), ("root",), 180),
        *(Case("12-crafted-policy", f"{k}-dynamics", crafted_policy(k, "dynamics"))
          for k in ("garbage", "empty", "pickle", "torch-pickle", "not-a-state-dict",
                    "wrong-shapes")),
        *(Case("12-crafted-policy", f"{k}-report", crafted_policy(k, "report"))
          for k in ("garbage", "torch-pickle")),
        Case("12-oversized", "result-json-dev-zero", oversized_record("result.json")),
        Case("12-oversized", "episodes-csv-dev-zero", oversized_record("episodes.csv")),
        *(Case("12-broken-pipe", c, broken_pipe(c)) for c in ("show", "export", "list")),
        Case("12-interrupted-report", "sigint-then-rerun", report_interrupted),
        *(Case("12-sigterm", c, sigterm(c)) for c in ("test", "report")),
        *(Case("12-memory-url", u.removeprefix("sqlite:///"), memory_url(u)) for u in MEMORY_URLS),
        Case("12-failed-command", "test-no-episode", failed_test_phase),
        Case("12-failed-command", "run-stage-test-first", failed_run_stage_test),
        *(Case("13-study-name", k, study_name(k))
          for k in ("escaping-evolve", "terminal-evolve", "escaping-shared", "terminal-shared")),
        *(Case("14-deep-yaml", c, deep_yaml(c)) for c in ("run", "hyperparams", "ppo", "suites-file")),
        *(Case("15-snapshot-edit", k, snapshot_edit(k)) for k in ("minimize", "infinity", "long-name")),
        *(Case("16-symlink-loop", c, symlink_loop(c)) for c in ("test", "report", "export")),
        *(Case("17-publish", k, publish_fault(k), ("root",), 300) for k in ("read-only", "full")),
        *(Case("18-python-api", k, python_call(k)) for k in PY_CALLS),
    ]  # fmt: skip
    return table


# Cheap cases that need no seed study: a few seconds each.
QUICK = [
    "11-experiment-file/latin-1",
    "11-experiment-file/python-tag",
    "12-memory-url/%253Amemory%253A",
]


# -- running the pass ----------------------------------------------------------------------------


def run_case(case: Case, seeds: Seeds, work: Path) -> dict[str, Any]:
    """Run one case in a fresh folder and classify what happened."""
    folder = work / f"{case.family}.{re.sub(r'[^A-Za-z0-9_.+-]', '_', case.name)}"
    folder.mkdir()
    ctx = Ctx(folder, seeds, case.timeout)
    start = time.monotonic()
    try:
        case.run(ctx)
    except Exception as err:  # the pass's own setup failed: reported, not counted
        ctx.other.append(f"pass error: {type(err).__name__}: {str(err).splitlines()[0][:150]}")
    tracebacks = [p.args[0] for p in ctx.procs if TRACEBACK in p.err + p.out]
    hangs = [p.args[0] for p in ctx.procs if p.hang]
    row = {
        "family": case.family,
        "case": case.name,
        "rc": " ".join(str(p.rc) for p in ctx.procs),
        "traceback": len(tracebacks),
        "bricked": int(bool(ctx.bricked)),
        "code-run": int(ctx.code_run),
        "files-left": int(bool(ctx.left)),
        "trials-lost": ctx.lost,
        "hang": len(hangs),
        "other": int(bool(ctx.other)),
        "seconds": round(time.monotonic() - start, 1),
    }
    problems = [
        *(f"traceback in {c}: {_traceback_tail(ctx.procs, c)}" for c in dict.fromkeys(tracebacks)),
        *(f"bricked: {b}" for b in ctx.bricked),
        *(["code ran from data"] if ctx.code_run else []),
        *(f"left {p}" for p in ctx.left),
        *([f"{ctx.lost} COMPLETE trial(s) lost"] if ctx.lost else []),
        *(f"hang: {c}" for c in hangs),
        *ctx.other,
    ]
    row["outcome"] = "; ".join(problems) or "ok"
    return row


def _traceback_tail(procs: list[Proc], command: str) -> str:
    for p in procs:
        if p.args[0] == command and TRACEBACK in p.err + p.out:
            return _last_line(p.err + p.out)
    return ""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", nargs="+", default=[],
                        help="run only cases whose family/name contains one of these")  # fmt: skip
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    parser.add_argument("--list", action="store_true", help="list the cases and exit")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for fault_pass.csv (default: a new temporary folder)")  # fmt: skip
    parser.add_argument("--keep", action="store_true", help="keep the cases' folders")
    args = parser.parse_args(argv)

    table = cases()
    if args.quick:
        table = [c for c in table if f"{c.family}/{c.name}" in QUICK]
    if args.cases:
        table = [c for c in table if any(s in f"{c.family}/{c.name}" for s in args.cases)]
    if args.list:
        for c in table:
            print(f"{c.family}/{c.name}" + (f"  (needs {', '.join(c.needs)})" if c.needs else ""))
        return 0
    out = args.out or Path(tempfile.mkdtemp(prefix="fault-pass-out-"))
    out.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix="fault-pass-"))
    seeds = Seeds(work, timeout=600)
    rows = []
    start = time.monotonic()
    try:
        for case in table:
            missing = [n for n in case.needs if not available(n)]
            if missing:
                row = {"family": case.family, "case": case.name, "rc": "", "seconds": 0.0,
                       "outcome": f"skipped (needs {', '.join(missing)})",
                       **dict.fromkeys((*COUNTS, "hang", "other"), "")}  # fmt: skip
            else:
                row = run_case(case, seeds, work)
            rows.append(row)
            print(f"{row['family']:<22} {row['case']:<30} rc {row['rc'] or '-':<12} "
                  f"{row['seconds']:>6.1f} s  {row['outcome']}", flush=True)  # fmt: skip
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    return report(rows, out, time.monotonic() - start)


def report(rows: list[dict[str, Any]], out: Path, seconds: float) -> int:
    """Print the summary table, write the CSV; 1 when any count is not 0."""
    ran = [r for r in rows if not str(r["outcome"]).startswith("skipped")]
    totals = {k: sum(int(r[k]) for r in ran) for k in (*COUNTS, "hang", "other")}
    print(f"\n{len(ran)} cases run, {len(rows) - len(ran)} skipped, in {seconds / 60:.1f} min")
    print("| count | value | cases |\n|---|---:|---|")
    for key, value in totals.items():
        names = [f"{r['family']}/{r['case']}" for r in ran if int(r[key])]
        print(f"| {key} | {value} | {', '.join(names) or '-'} |")
    path = out / "fault_pass.csv"
    fields = ["family", "case", "rc", *COUNTS, "hang", "other", "seconds", "outcome"]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")
    return int(any(totals.values()))


if __name__ == "__main__":
    raise SystemExit(main())
