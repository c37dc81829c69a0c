"""Bad input is refused with one line on stderr and exit code 2, before anything is written."""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import subprocess
from pathlib import Path

import pytest

from ermrl.cli._evolve import evolve_main
from ermrl.cli._generalization import evolve_generalization_main

FAST = ["--n-trials", "1", "--n-seeds", "1", "--training-steps", "64", "--quiet"]


@pytest.fixture(autouse=True)
def _no_training(monkeypatch):  # noqa: ANN001, ANN202
    """Input that gets past validation must not train (``--training-steps 1e30`` would run
    forever on code without the limit): the study is created, then the run is skipped, and the
    test sees the database file it must not find."""
    import ermrl.runner._commands

    monkeypatch.setattr(ermrl.runner._commands, "run_and_report", lambda *a, **k: 0)


def _refused(main, argv, capsys) -> str:  # noqa: ANN001
    """Run a CLI entry point in-process; assert exit 2 and a single stderr line."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    return err


def _evolve(tmp_path, *extra: str) -> list[str]:  # noqa: ANN001
    db = tmp_path / "s.db"
    return ["--env-id", "Pendulum-v1", *FAST, "--storage", f"sqlite:///{db}", *extra]


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--ppo", "n_steps=0"], "n_steps"),
        (["--ppo", "n_steps=1", "n_envs=1"], "n_steps"),
        (["--ppo", "learning_rate=abc"], "learning_rate"),
        (["--ppo", "learning_rate=-1"], "learning_rate"),
        (["--ppo", "learning_rate=lin_abc"], "learning_rate"),
        (["--ppo", "batch_size=0"], "batch_size"),
        (["--ppo", "policy_kwargs={net_arch: foo}"], "refused"),
        (["--ppo", "policy_kwargs={activation_fn: nn.ReLU}"], "tanh, relu, elu, leaky_relu"),
        (["--ppo", "gamma=2"], "gamma"),
        (["--ppo", "n_steps=100000000"], "n_steps * n_envs"),
        (["--units", "1e9"], "units"),
        (["--units", "5000", "--n-reservoirs", "3"], "units"),
        (["--training-steps", "1e30"], "training steps"),
        (["--training-steps", "1e400"], "integer"),
        (["--n-trials", "1e7"], "n_trials"),
        (["--n-seeds", "5000"], "seeds"),
        (["--bias-scaling", "nan"], "bias_scaling"),
        (["--bias-scaling", "inf"], "bias_scaling"),
        (["--n-envs", "100000"], "n_envs"),
    ],
)
def test_evolve_refuses_bad_values_before_the_study_exists(tmp_path, capsys, extra, expected):  # noqa: ANN001
    """Values that used to fail only inside the first trial (after the study and a FAIL trial
    were stored) are refused up front: exit 2, one line, no database file."""
    err = _refused(evolve_main, _evolve(tmp_path, *extra), capsys)
    assert expected in err
    assert not (tmp_path / "s.db").exists()


@pytest.mark.parametrize("env_id", [".:Pendulum-v1", ":Pendulum-v1", "..x:Pendulum-v1"])
def test_evolve_refuses_malformed_module_prefix(tmp_path, capsys, env_id):  # noqa: ANN001
    argv = _evolve(tmp_path)
    argv[1] = env_id
    err = _refused(evolve_main, argv, capsys)
    assert "not a module name" in err
    assert not (tmp_path / "s.db").exists()


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("Pendulum-v1: {n_steps: [\n", "not valid plain YAML"),
        ("Pendulum-v1: !!python/object/apply:os.system ['echo hacked']\n", "not valid plain YAML"),
        ("Pendulum-v1: 5\n", "must be a mapping"),
        ("Pendulum-v1: {policy_kwargs: {activation_fn: os.system}}\n", "is not one of tanh"),
        ("- 1\n- 2\n", "must map env ids"),
    ],
)
def test_evolve_refuses_malformed_hyperparams_file(tmp_path, capsys, text, expected):  # noqa: ANN001
    table = tmp_path / "ppo.yml"
    table.write_text(text)
    err = _refused(evolve_main, _evolve(tmp_path, "--hyperparams", str(table)), capsys)
    assert expected in err
    assert "hacked" not in capsys.readouterr().out
    assert not (tmp_path / "s.db").exists()


# -- evolve-generalization ------------------------------------------------------------------------


def _generalization(tmp_path, *extra: str) -> list[str]:  # noqa: ANN001
    db = tmp_path / "s.db"
    return ["--env-ids", "Swimmer-v5", "Hopper-v5", *FAST, "--storage", f"sqlite:///{db}", *extra]


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--ppo", "n_steps=0"], "n_steps"),
        (["--ppo", "learning_rate=abc"], "learning_rate"),
        (["--ppo", "policy_kwargs={net_arch: foo}"], "refused"),
        (["--units", "1e9"], "units"),
        (["--training-steps", "1e30"], "training steps"),
    ],
)
def test_evolve_generalization_refuses_bad_values_before_the_study_exists(
    tmp_path, capsys, extra, expected
):  # noqa: ANN001

    err = _refused(evolve_generalization_main, _generalization(tmp_path, *extra), capsys)
    assert expected in err
    assert not (tmp_path / "s.db").exists()


def test_malformed_suites_file_is_one_line(tmp_path, capsys):  # noqa: ANN001
    """PyYAML's parse error spans several lines (the line and a caret); the CLI gives one."""

    suites = tmp_path / "suites.yml"
    suites.write_text("mine: [Hopper-v5,\n  other: {\n")
    argv = ["--suite", "mine", "--suites-file", str(suites), *FAST]
    err = _refused(
        evolve_generalization_main, [*argv, "--storage", f"sqlite:///{tmp_path}/s.db"], capsys
    )
    assert "not valid YAML" in err
    assert not (tmp_path / "s.db").exists()


# -- deeply nested YAML ---------------------------------------------------------------------------


@pytest.mark.parametrize("reader", ["run", "hyperparams", "ppo", "suites"])
def test_deeply_nested_yaml_is_one_line(tmp_path, capsys, reader):  # noqa: ANN001
    """``[[[...]]]`` 500 deep used to stop every YAML reader with a RecursionError traceback;
    each reads through ``ermrl._io.load_yaml``, which refuses nesting past its limit."""
    from ermrl.cli._run import run_main

    deep = tmp_path / "d.yaml"
    deep.write_text("a: " + "[" * 500 + "]" * 500 + "\n")
    argv = {
        "run": (run_main, [str(deep), "--dry-run"]),
        "hyperparams": (evolve_main, _evolve(tmp_path, "--hyperparams", str(deep))),
        "ppo": (evolve_main, _evolve(tmp_path, "--ppo", "policy_kwargs=" + "[" * 600 + "]" * 600)),
        "suites": (
            evolve_generalization_main,
            [*_generalization(tmp_path, "--suites-file", str(deep))[3:], "--suite", "a"],
        ),
    }
    main, args = argv[reader]
    err = _refused(main, args, capsys)
    assert "nested deeper than 50 levels" in err and "line 1" in err, err
    assert not (tmp_path / "s.db").exists()


def test_every_yaml_reader_goes_through_load_yaml() -> None:
    """The depth limit is checked in one place: no other module calls PyYAML's loaders."""
    import re

    root = Path(__file__).resolve().parents[1] / "ermrl"
    calls = re.compile(r"yaml\.(safe_load|load|full_load|unsafe_load|load_all|safe_load_all)\(")
    found = [
        str(path.relative_to(root))
        for path in root.rglob("*.py")
        if path.name != "_io.py" and calls.search(path.read_text())
    ]
    assert found == []


# -- test phase -----------------------------------------------------------------------------------


@pytest.fixture
def study_url(tmp_path):  # noqa: ANN001, ANN201
    """A Pendulum study without trials (``--agents ppo`` needs none); nothing is trained."""
    url = f"sqlite:///{tmp_path / 'study.db'}"
    assert evolve_main([*_evolve(tmp_path)[:-2], "--storage", url, "--study-name", "s"]) == 0
    return url


def _test_argv(url: str, out, *extra: str) -> list[str]:  # noqa: ANN001
    return [
        *("--study-name", "s", "--storage", url, "--agents", "ppo", "--seeds", "100"),
        *("--training-steps", "64", "--quiet", "--out", str(out), *extra),
    ]


@contextlib.contextmanager
def _tmpfs(where, *options: str):  # noqa: ANN001, ANN202
    """Mount a small tmpfs at ``where`` (needs root; the test is skipped otherwise)."""
    where.mkdir()
    proc = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", ",".join(options), "tmpfs", str(where)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs to fill up (needs root): {proc.stderr.strip()}")
    try:
        yield where
    finally:
        subprocess.run(["umount", "--lazy", str(where)], check=False)


def test_test_out_is_a_file(study_url, tmp_path, capsys):  # noqa: ANN001
    from ermrl.cli._test import test_main

    out = tmp_path / "results"
    out.write_text("mine\n")
    err = _refused(test_main, _test_argv(study_url, out), capsys)
    assert "is a file" in err
    assert out.read_text() == "mine\n"
    err = _refused(test_main, _test_argv(study_url, out / "sub"), capsys)
    assert "is a file" in err


@pytest.mark.parametrize("under", ["", "sub"])
def test_test_out_on_a_symlink_loop(study_url, tmp_path, capsys, under):  # noqa: ANN001
    """``ln -s loop loop; ermrl test --out loop`` (or ``loop/sub``) used to stop with a
    FileExistsError traceback; ``report``, ``export`` and ``evolve`` already said it in one line.
    Nothing is written, and the link stays as it was."""
    from ermrl.cli._test import test_main

    loop = tmp_path / "loop"
    loop.symlink_to("loop")
    before = sorted(p.name for p in tmp_path.iterdir())
    err = _refused(test_main, _test_argv(study_url, loop / under if under else loop), capsys)
    assert f"{loop} is a symbolic link that cannot be followed (Too many levels" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert os.readlink(loop) == "loop"


def test_test_out_read_only(study_url, tmp_path, capsys):  # noqa: ANN001
    from ermrl.cli._test import test_main

    with _tmpfs(tmp_path / "ro", "ro", "size=1m") as ro:
        err = _refused(test_main, _test_argv(study_url, ro / "out"), capsys)
        assert "cannot write" in err and "read-only" in err


def test_test_refuses_bad_ppo_override_before_writing(study_url, tmp_path, capsys):  # noqa: ANN001
    from ermrl.cli._test import test_main

    out = tmp_path / "out"
    for bad in ("n_steps=0", "learning_rate=abc", "policy_kwargs={net_arch: foo}"):
        err = _refused(test_main, _test_argv(study_url, out, "--ppo", bad), capsys)
        assert bad.partition("=")[0] in err or "refused" in err
        assert not out.exists()


def test_test_on_a_full_disk(study_url, tmp_path, capsys):  # noqa: ANN001
    """A real full disk (a 64 KiB tmpfs; PPO's model.zip is larger): one line, exit 2, and no
    truncated model.zip (nor temporary file) left behind."""
    from ermrl.cli._test import test_main

    with _tmpfs(tmp_path / "full", "size=64k") as full:
        out = full / "out"
        err = _refused(test_main, _test_argv(study_url, out), capsys)
        assert "No space left on device" in err
        folder = out / "agents" / "ppo" / "seed_100"
        assert not (folder / "model.zip").exists()
        leftovers = [p.name for p in out.rglob("*") if p.is_file()]
        assert not [n for n in leftovers if n.startswith(".") or n.endswith(".partial")], leftovers


# -- write_atomic ---------------------------------------------------------------------------------


def test_write_atomic_on_a_full_disk_leaves_nothing_behind(tmp_path):  # noqa: ANN001
    """A real full disk (a 64 KiB tmpfs): the old file stays whole and no temporary file stays."""
    from ermrl._io import write_atomic

    with _tmpfs(tmp_path / "full", "size=64k") as full:
        target = full / "summary.csv"
        write_atomic(target, "old\n")
        with pytest.raises(OSError) as exc:
            write_atomic(target, "x" * 200_000)
        assert exc.value.errno == errno.ENOSPC
        assert target.read_text() == "old\n"
        assert [p.name for p in full.iterdir()] == ["summary.csv"]


@pytest.mark.parametrize(("umask", "mode"), [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_write_atomic_respects_the_umask(tmp_path, umask, mode):  # noqa: ANN001
    """Files are readable by the group/others the umask allows (mkstemp alone gives 0600)."""
    from ermrl._io import write_atomic

    old = os.umask(umask)
    try:
        write_atomic(tmp_path / "summary.csv", "a,b\n")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "summary.csv").stat().st_mode) == mode


# -- the stored command ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("main", "prog", "argv"),
    [
        (evolve_main, "ermrl evolve", ["--env-id", "Pendulum-v1"]),
        (evolve_main, "evolve_res.py", ["--env-id", "Pendulum-v1"]),
        (evolve_generalization_main, "ermrl evolve-generalization", ["--env-ids", "Hopper-v5"]),
    ],
)
def test_stored_command_can_be_pasted_into_a_shell(tmp_path, main, prog, argv):  # noqa: ANN001
    """``shlex.join(["ermrl evolve", ...])`` gave ``'ermrl evolve' --env-id ...``, which a shell
    runs as one (missing) program; each word of the program name is now its own word."""
    import shlex

    import optuna

    url = f"sqlite:///{tmp_path / 'my study.db'}"
    full = [*argv, *FAST, "--storage", url, "--study-name", "s"]
    assert main(full, prog=prog) == 0
    command = optuna.load_study(study_name="s", storage=url).user_attrs["ermrl_command"]
    assert command.startswith(f"{prog} {argv[0]} ")
    assert shlex.split(command) == [*prog.split(), *full]


# -- SIGTERM between trials -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("signame", "code", "expected"),
    [
        ("SIGTERM", 143, "stopped by SIGTERM between trials"),
        ("SIGINT", 130, "interrupted between trials"),
    ],
)
def test_signal_while_waiting_says_no_trial_was_running(
    tmp_path, monkeypatch, capsys, signame, code, expected
):  # noqa: ANN001
    """A worker that has reached the budget waits for another worker's running trial; a signal
    then closes nothing, and the message must not claim that a trial was closed (and queued)."""
    import signal
    import sys
    import threading

    import optuna

    from ermrl.cli import run_command

    url = f"sqlite:///{tmp_path / 's.db'}"
    argv = [*_evolve(tmp_path)[:-2], "--storage", url, "--study-name", "s", "--no-reference-trial"]
    assert evolve_main(argv) == 0  # creates the study (training stubbed by _no_training)
    monkeypatch.undo()  # the real run_and_report from here on
    study = optuna.load_study(study_name="s", storage=url)
    study.tell(study.ask(), 0.0)  # the budget (1 trial) is spent...
    study.ask()  # ...and another worker's trial is running
    capsys.readouterr()
    timer = threading.Timer(2.0, os.kill, (os.getpid(), getattr(signal, signame)))
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    hook = sys.unraisablehook
    timer.start()
    try:
        # As the command runs: its start-up notes a signal that a library drops (a weakref
        # callback under load), and the worker raises it again once its own handler is in.
        returned = run_command("evolve", argv)
    finally:
        timer.cancel()
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        sys.unraisablehook = hook
    assert returned == code
    err = capsys.readouterr().err
    assert expected in err, err
    assert "closed as FAIL" not in err and "queued again" not in err
    states = [t.state.name for t in optuna.load_study(study_name="s", storage=url).trials]
    assert states == ["COMPLETE", "RUNNING"]  # the other worker's trial is untouched


# -- report ---------------------------------------------------------------------------------------


def test_report_on_a_study_without_completed_trials(study_url, tmp_path, capsys):  # noqa: ANN001
    """An empty study used to give exit 0 and a report of empty figures."""
    from ermrl.cli._report import report_main

    out = tmp_path / "report"
    argv = ["--study-name", "s", "--storage", study_url, "--out", str(out), "--quiet"]
    err = _refused(report_main, argv, capsys)
    assert "no completed trial" in err
    assert not out.exists()


@pytest.mark.parametrize("value", ["abc", "1.5", "[1]", ".inf", ".nan"])
def test_n_envs_must_be_a_whole_number(tmp_path, capsys, value):  # noqa: ANN001
    err = _refused(evolve_main, _evolve(tmp_path, "--ppo", f"n_envs={value}"), capsys)
    assert "n_envs" in err
    assert not (tmp_path / "s.db").exists()


# -- the study name -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "expected"), [("", "empty"), ("   ", "empty"), ("s" * 513, "512 characters")]
)
def test_evolve_refuses_a_bad_study_name(tmp_path, capsys, name, expected):  # noqa: ANN001
    """An empty name would silently become the default one; Optuna's study_name column holds
    512 characters (MySQL fails with a DataError traceback on longer)."""
    err = _refused(evolve_main, _evolve(tmp_path, "--study-name", name), capsys)
    assert "--study-name" in err and expected in err
    assert list(tmp_path.iterdir()) == []


def test_a_512_character_study_name_is_accepted(tmp_path):  # noqa: ANN001
    assert evolve_main(_evolve(tmp_path, "--study-name", "s" * 512)) == 0


@pytest.mark.parametrize(
    ("name", "expected"),
    [("", "--study-name"), (" ", "--study-name"), ("s" * 513, "no study named 'sss")],
)
def test_test_and_report_refuse_a_bad_study_name(study_url, tmp_path, capsys, name, expected):  # noqa: ANN001
    """A blank name is refused by the parser; a name that ermrl would not create (too long
    here) is still looked up, since a study another tool named can be read (and is not there)."""
    from ermrl.cli._report import report_main
    from ermrl.cli._test import test_main

    out = tmp_path / "out"
    err = _refused(
        test_main, _test_argv(url=study_url, out=out)[2:] + ["--study-name", name], capsys
    )
    assert expected in err
    argv = ["--storage", study_url, "--study-name", name, "--out", str(out)]
    assert expected in _refused(report_main, argv, capsys)
    assert not out.exists()


# -- study export ---------------------------------------------------------------------------------


def _fill(folder) -> None:  # noqa: ANN001
    """Write into ``folder`` (a small tmpfs) until it is full."""
    with open(folder / "filler", "wb", buffering=0) as handle, contextlib.suppress(OSError):
        while True:
            handle.write(b"\0" * 4096)


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".json"])
@pytest.mark.parametrize("where", ["read-only", "full"])
def test_study_export_that_cannot_be_written(study_url, tmp_path, capsys, suffix, where):  # noqa: ANN001
    """A read-only folder or a full disk (real tmpfs mounts: root ignores chmod): one line,
    exit 2, no partial or temporary file, and an earlier export left whole."""
    from ermrl.cli._study import study_main

    if suffix == ".parquet":
        pytest.importorskip("pyarrow")
    options = ("ro",) if where == "read-only" else ("size=64k",)
    with _tmpfs(tmp_path / "mnt", *options) as folder:
        out = folder / f"trials{suffix}"
        if where == "full":
            out.write_text("an earlier export\n")
            _fill(folder)
        argv = ["export", "--storage", study_url, "--study-name", "s", "--out", str(out)]
        err = _refused(study_main, argv, capsys)
        assert f"cannot write {out}" in err
        reason = "Read-only file system" if where == "read-only" else "No space left on device"
        assert reason in err
        if where == "full":
            assert out.read_text() == "an earlier export\n"
            assert sorted(p.name for p in folder.iterdir()) == ["filler", out.name]
        else:
            assert list(folder.iterdir()) == []


# -- report --out ---------------------------------------------------------------------------------


@pytest.fixture
def reported_study_url(study_url):  # noqa: ANN001, ANN201
    """``study_url`` with three completed trials (told by hand: nothing is trained)."""
    import optuna

    from ermrl.config import EvolveConfig, from_dict
    from ermrl.search._study import sample_params

    study = optuna.load_study(study_name="s", storage=study_url)
    config = from_dict(EvolveConfig, study.user_attrs["ermrl_config"])
    for i in range(3):
        trial = study.ask()
        sample_params(trial, config.space)
        study.tell(trial, -100.0 - i)
    return study_url


@pytest.mark.parametrize("where", ["read-only", "full"])
def test_report_that_cannot_be_written(reported_study_url, tmp_path, capsys, where):  # noqa: ANN001
    """A read-only folder or a full disk under --out (real tmpfs mounts: root ignores chmod
    0555): one line, exit 2, no partial report or staging folder, and an earlier report's file
    left whole."""
    from ermrl.cli._report import report_main

    options = ("ro",) if where == "read-only" else ("size=64k",)
    with _tmpfs(tmp_path / "mnt", *options) as folder:
        out = folder / "report"
        if where == "full":
            out.mkdir()
            (out / "report.md").write_text("an earlier report\n")
            _fill(folder)
        argv = ["--study-name", "s", "--storage", reported_study_url, "--out", str(out)]
        err = _refused(report_main, [*argv, "--quiet", "--no-interactive"], capsys)
        assert f"cannot write the report {out}" in err and "nothing was written" in err
        reason = "Read-only file system" if where == "read-only" else "No space left on device"
        assert reason in err
        if where == "full":
            assert sorted(p.name for p in folder.iterdir()) == ["filler", "report"]
            assert [p.name for p in out.iterdir()] == ["report.md"]
            assert (out / "report.md").read_text() == "an earlier report\n"
        else:
            assert list(folder.iterdir()) == []


# -- dynamics --out -------------------------------------------------------------------------------


def _tiny_recording():  # noqa: ANN202
    """A synthetic 64-step recording (nothing is trained or replayed)."""
    import numpy as np

    from ermrl.analysis import DynamicsRecording

    rng = np.random.default_rng(0)
    return DynamicsRecording(
        observations=rng.normal(size=(64, 3)),
        actions=rng.normal(size=(64, 1)),
        rewards=rng.normal(size=64),
        states=np.tanh(rng.normal(size=(64, 8))),
        dt=0.05,
        env_id="Pendulum-v1",
        observe="all",
        agent="res-ppo",
        seed=10,
        obs_indices=np.arange(3),
    )


@pytest.mark.parametrize("where", ["read-only", "full"])
def test_dynamics_that_cannot_be_written(tmp_path, capsys, monkeypatch, where):  # noqa: ANN001
    """A read-only folder or a full disk under --out (real tmpfs mounts: root ignores chmod
    0555; the episode is a synthetic recording): one line, exit 2, no partial file."""
    import ermrl.analysis
    from ermrl.cli._dynamics import dynamics_main

    monkeypatch.setattr(ermrl.analysis, "record_dynamics", lambda **kwargs: _tiny_recording())
    options = ("ro",) if where == "read-only" else ("size=64k",)
    with _tmpfs(tmp_path / "mnt", *options) as folder:
        out = folder / "dynamics"
        if where == "full":
            _fill(folder)
        argv = ["--run", str(tmp_path), "--out", str(out), "--quiet"]
        err = _refused(dynamics_main, argv, capsys)
        assert f"cannot write {out}" in err and "nothing was written" in err
        reason = "Read-only file system" if where == "read-only" else "No space left on device"
        assert reason in err
        assert sorted(p.name for p in folder.iterdir()) == (
            [] if where == "read-only" else ["filler"]
        )


def test_staged_folder_keeps_other_files_and_leaves_nothing_on_error(tmp_path):  # noqa: ANN001
    """Files the block did not write stay; an error leaves the folder as it was, and creates
    no folder (a full disk is simulated by raising ENOSPC inside the block)."""
    from ermrl._io import staged_folder

    out = tmp_path / "report"
    (out / "figures").mkdir(parents=True)
    (out / "notes.txt").write_text("mine\n")
    (out / "figures" / "a.png").write_text("old\n")
    with staged_folder(out) as stage:
        (stage / "figures").mkdir()
        (stage / "figures" / "a.png").write_text("new\n")
        (stage / "report.md").write_text("# report\n")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == [
        "figures",
        "figures/a.png",
        "notes.txt",
        "report.md",
    ]
    assert (out / "figures" / "a.png").read_text() == "new\n"
    with pytest.raises(OSError), staged_folder(out) as stage:
        (stage / "report.md").write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert (out / "report.md").read_text() == "# report\n"
    assert len(list(out.rglob("*"))) == 4
    fresh = tmp_path / "new" / "deeper"
    with pytest.raises(OSError), staged_folder(fresh) as stage:
        raise OSError(errno.ENOSPC, "No space left on device")
    assert not (tmp_path / "new").exists()


def test_a_staging_folder_left_by_a_killed_process_is_removed_by_the_next_run(tmp_path):  # noqa: ANN001
    """kill -9 during a report leaves its hidden staging folder; the next report of the same
    folder removes it, and leaves a live process's (or another machine's) alone."""
    import sys
    import time

    from ermrl._io import _host, staged_folder

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "report"
    left = tmp_path / f".report.{_host()}.{dead.pid}.abcd_123"
    live = tmp_path / f".report.{_host()}.{os.getpid()}.live0000"
    other = tmp_path / f".report.elsewhere.{dead.pid}.other000"
    legacy = tmp_path / ".report.old_1234"  # named before the process was in the name
    for folder in (left, live, other, legacy):
        (folder / "figures").mkdir(parents=True)
    day_ago = time.time() - 2 * 86_400
    os.utime(legacy, (day_ago, day_ago))
    with staged_folder(out) as stage:
        (stage / "report.md").write_text("# report\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live.name, other.name, "report"])


@pytest.mark.parametrize(
    "command",
    [
        ["study", "show", "--study-name", "s"],
        ["study", "export", "--study-name", "s", "--out", "-"],
    ],
    ids=["show", "export"],
)
def test_a_reader_that_closes_the_pipe_ends_the_command_quietly(tmp_path, command):  # noqa: ANN001
    """``ermrl study show | grep -q x`` or ``study export --out - | head``: no traceback."""
    import sys

    import optuna

    url = f"sqlite:///{tmp_path / 's.db'}"
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name="s", storage=url)
    for i in range(3):
        study.tell(study.ask({"x": optuna.distributions.FloatDistribution(0, 1)}), float(i))
    proc = subprocess.Popen(
        [sys.executable, "-m", "ermrl", *command, "--storage", url],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=tmp_path,
    )
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # the reader is gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait(120) == 141, err
    assert err == ""


def _study_with_config(tmp_path):  # noqa: ANN001, ANN202
    """A study of a tiny Pendulum configuration with one COMPLETE trial (nothing trained)."""
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

    space = ReservoirSpace(units=10)
    problem = Problem(
        task=TaskConfig("Pendulum-v1", "positions"),
        encoder=EncoderConfig(reservoirs=space.default_reservoirs()),
        ppo=PPOConfig(hyperparams={"n_steps": 128, "batch_size": 64}),
        budget=BudgetConfig(training_steps=256),
        seeds=(0,),
    )
    config = EvolveConfig(problem=problem, space=space, search=SearchConfig(n_trials=4))
    url = f"sqlite:///{tmp_path / 's.db'}"
    study = create_or_resume_study(config, url, "s", heartbeat_interval=None)
    for value in (-900.0, -800.0, -1000.0, -700.0):
        trial = study.ask()
        sample_params(trial, space)
        study.tell(trial, value)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    return url


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (Linux ``/proc``)."""
    return [
        int(child)
        for task in Path(f"/proc/{pid}/task").iterdir()
        for child in (task / "children").read_text().split()
    ]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ")
    except OSError:
        return ""


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (a zombie not yet reaped counts as ended)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return True
    return "\nState:\tZ" in status


@pytest.mark.slow  # three command start-ups (torch, gymnasium), about 10 s each
@pytest.mark.parametrize("command", ["report", "test", "population-test"])
def test_sigterm_during_report_or_test_is_one_line_and_leaves_no_partial_folder(tmp_path, command):  # noqa: ANN001
    """SIGTERM (kill, a SLURM time limit) while the command writes: one line, exit 143, and
    no staging folder or partial report left behind (they died silently before). A population
    split over 2 processes stops them too: the command used to say it stopped, then wait for
    their hours of training to end before it exited."""
    import signal
    import sys
    import time

    url = _study_with_config(tmp_path)
    out = tmp_path / "out"
    pool = ["--backend", "population", "--n-procs", "2"]
    args = {
        "report": ["report", "--no-interactive", "--no-html", "--no-dynamics"],
        "test": ["test", "--agents", "ppo", "--seeds", "1", "--training-steps", "200000"],
        "population-test": ["test", "--agents", "ppo", "--seeds", "1", "2", "--training-steps",
                            "50000000", "--progress", "none", *pool],
    }[command]  # fmt: skip
    proc = subprocess.Popen(
        [sys.executable, "-m", "ermrl", *args, "--study-name", "s", "--storage", url,
         "--out", str(out)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
    )  # fmt: skip
    # The report is stage-written into a hidden folder; the test trains in out/.
    started = (
        (lambda: any(p.name.startswith(".out.") for p in tmp_path.iterdir()))
        if command == "report"
        else (lambda: (out / "config.yaml").exists())
    )
    workers: list[int] = []
    deadline = time.monotonic() + 120
    while proc.poll() is None and not started() and time.monotonic() < deadline:
        time.sleep(0.02)
    if command == "population-test":  # SIGTERM once both parts train, to this process only
        while proc.poll() is None and len(workers) < 2 and time.monotonic() < deadline:
            workers = [c for c in _children(proc.pid) if "spawn_main" in _cmdline(c)]
            time.sleep(0.2)
        assert len(workers) == 2, workers
    assert proc.poll() is None, proc.communicate()[1]
    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"still running 120 s after SIGTERM:\n{proc.communicate()[1]}")
    assert proc.returncode == 143, err
    assert all(_gone(w) for w in workers), [w for w in workers if not _gone(w)]
    assert len(err.strip().splitlines()) == 1 and "stopped by SIGTERM" in err, err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    if command == "report":
        assert not out.exists()
    else:
        assert f"finished runs are kept in {out}" in err


@pytest.mark.parametrize("signum", ["SIGTERM", "SIGINT"])
def test_a_signal_dropped_in_a_weakref_callback_still_stops_the_report(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, signum: str
) -> None:
    """The signal lands in a weakref callback, whose exception Python prints as "Exception
    ignored in" and drops (a report once ran to the end after a SIGTERM this way, exit 0).
    Nothing is mocked: the callback really raises the signal while the report writes. The
    command still stops before it publishes the report: one line, exit 143 or 130."""
    import signal
    import sys
    import weakref

    from ermrl.analysis import _report
    from ermrl.cli import run_command

    url = _study_with_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    # run_command installs its handlers and Python's unraisable hook in this process: restored
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    real = _report._study_section
    calls = []

    def study_section_then_signal(state):  # noqa: ANN001, ANN202
        class Owner:
            pass

        owner = Owner()
        ref = weakref.ref(owner, lambda _: signal.raise_signal(getattr(signal, signum)))
        del owner  # the callback runs here; Python drops its exception
        calls.append(ref)
        return real(state)

    monkeypatch.setattr(_report, "_study_section", study_section_then_signal)
    out = tmp_path / "out"
    try:
        code = run_command(
            "report",
            ["--study-name", "s", "--storage", url, "--out", str(out), "--no-interactive",
             "--no-html", "--no-dynamics"],
        )  # fmt: skip
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    err = capsys.readouterr().err
    assert calls, "the report did not reach its first section"
    assert code == {"SIGTERM": 143, "SIGINT": 130}[signum], err
    assert err.strip().splitlines() == [
        "ermrl report: "
        + ("stopped by SIGTERM" if signum == "SIGTERM" else "interrupted")
        + "; no report written"
    ], err
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_failed_test_phase_leaves_no_skeleton_folder(tmp_path, monkeypatch, capsys):  # noqa: ANN001
    """A test phase that fails before any run finishes (here no episode ends within the
    budget) removes the folders it created; only its one-line error remains."""
    from ermrl.cli import test_main

    url = _study_with_config(tmp_path)
    monkeypatch.chdir(tmp_path)
    argv = ["--study-name", "s", "--storage", url, "--agents", "ppo", "--seeds", "1"]
    with pytest.raises(SystemExit) as info:
        test_main([*argv, "--training-steps", "64", "--progress", "none"])
    assert info.value.code == 2
    assert "no episode of Pendulum-v1 ended" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.db", "s.db.lock"]


def test_a_sqlite_study_on_a_full_disk_during_evolve_is_one_line(tmp_path, monkeypatch, capsys):  # noqa: ANN001
    """The disk under a SQLite study fills up while a worker runs (a real tmpfs): one line
    with SQLite's own reason, not Optuna's traceback blaming "exceeding max length"."""
    import ermrl.cli._evolve

    with _tmpfs(tmp_path / "mnt", "size=600k") as folder:
        url = f"sqlite:///{folder / 's.db'}"
        argv = ["--env-id", "Pendulum-v1", *FAST, "--storage", url, "--study-name", "s"]
        assert evolve_main(argv) == 0  # creates the study (training stubbed)
        monkeypatch.undo()  # the real run from here on
        _fill(folder)
        err = _refused(ermrl.cli._evolve.evolve_main, argv, capsys)
        assert "database or disk is full" in err and "exceeding max length" not in err, err
        assert f"cannot write to {url}" in err
