"""An experiment's plain-file state, carried between machines: study snapshots and finished runs.

``ermrl run`` publishes what a later sitting on another machine needs, as plain files that a
repository keeps (never databases or models): each evolution study as one JSON snapshot, and
each finished test run's ``settings.json``, ``episodes.csv`` and ``result.json``. The next
``ermrl run`` of the file imports the snapshots, puts the runs back and goes on; its plan
already counts them (`snapshot_status`, `published_runs_status`).

Every published file is written to a temporary name and renamed (`ermrl._io.write_atomic`),
so a reader of the folder never sees half a file. Publishing copies results that stay in the
experiment's own folders: a published folder that cannot be written (read-only, full) is one
line saying what was not published (`publish_results`), the experiment goes on, and the next
run of the file publishes again.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ermrl._io import write_atomic
from ermrl.runner._experiment import (
    ExperimentError,
    ExperimentFile,
    Step,
    _study,
    format_duration,
    snapshot_path,
)

__all__ = [
    "PUBLISH_MAX_BYTES",
    "PeriodicSnapshots",
    "import_snapshots",
    "publish_finished_runs",
    "publish_results",
    "publish_step",
    "published_runs_status",
    "restore_finished_runs",
    "snapshot_status",
    "write_snapshot_files",
    "write_snapshots",
]


def publish_step(
    exp: ExperimentFile, step: Step, max_bytes: int | None = None
) -> tuple[list[Path], list[Path]]:
    """Copy a finished test or report step's plain files to ``exp.publish``.

    Plain files only (CSV, JSON, Markdown, HTML, PNG, YAML, TXT), never models or arrays; the
    test folder's per-run ``result.json`` files keep their ``agents/<agent>/seed_<s>/`` layout.
    A file over ``max_bytes`` (default `PUBLISH_MAX_BYTES`) is left out: the published
    folder is meant for version control, and the one such file a report writes is its
    self-contained ``report.html`` (figures embedded), whose ``report.md`` and PNGs are
    published beside it.

    Returns:
        ``(written, left_out)``: the files written, and the files too large to publish.

    Raises:
        OSError: a file cannot be written; the files already published stay whole.
    """
    if exp.publish is None or step.folder is None or not step.folder.exists():
        return [], []
    limit = PUBLISH_MAX_BYTES if max_bytes is None else max_bytes
    dest = exp.publish / step.label / step.stage
    written, left_out = [], []
    for src in sorted(step.folder.rglob("*")):
        if not src.is_file() or src.suffix.lower() not in _PLAIN or src.name.startswith("."):
            continue
        if src.stat().st_size > limit:
            left_out.append(src)
            continue
        rel = src.relative_to(step.folder)
        target = dest / rel
        _copy(src, target)
        written.append(target)
    return written, left_out


def _copy(src: Path, dest: Path) -> None:
    """Copy a file under a temporary name renamed to ``dest``, unless ``dest`` is the same."""
    data = src.read_bytes()
    if not (dest.is_file() and dest.read_bytes() == data):
        write_atomic(dest, data)


def publish_results(exp: ExperimentFile, step: Step, stream: Any, finished: bool = True) -> None:
    """Publish what a step leaves; what was not published is one line, never an error.

    A finished evolution writes its study snapshot (`write_snapshots`), a finished test or
    report step its plain files (`publish_step`), and a test step that stopped its finished
    runs (`publish_finished_runs`, ``finished=False``). A file too large to publish is one
    line on ``stream``; a published folder that cannot be written (read-only, full) is one
    line on stderr: the results stay in ``exp.out`` and the next run of the file publishes
    them (a finished step publishes again when a run skips it).
    """
    if exp.publish is None:
        return
    try:
        if not finished:
            publish_finished_runs(exp, step)
        elif step.stage == "evolve":
            write_snapshots(exp, [step])
        elif step.stage in ("test", "report"):
            for path in publish_step(exp, step)[1]:
                print(
                    f"not published: {path} ({path.stat().st_size / 2**20:.1f} MiB, over "
                    f"{PUBLISH_MAX_BYTES / 2**20:.0f} MiB); it stays in {exp.out}",
                    file=stream,
                    flush=True,
                )
    except OSError as err:
        what, kept = (
            ("study snapshot", exp.storage) if step.stage == "evolve" else (step.stage, exp.out)
        )
        print(
            f"not published: the {what} of {step.label} to {exp.publish} "
            f"({err.strerror or err}); kept in {kept}, the next run publishes it",
            file=sys.stderr,
            flush=True,
        )


_PLAIN = {".csv", ".json", ".md", ".html", ".png", ".yaml", ".yml", ".txt"}
# The largest file ``ermrl run`` publishes (1 MiB): what a repository keeps comfortably.
PUBLISH_MAX_BYTES = 1 << 20


# ---------------------------------------------------------------------------------------------
# Snapshots: a study as one plain JSON file, so a run continues on another machine


def write_snapshots(exp: ExperimentFile, steps: Sequence[Step]) -> list[tuple[Step, Path, int]]:
    """Write a snapshot of every evolution study that exists (and its re-evaluation study).

    A study is read while workers may still write to it: what was COMPLETE stays so, and the
    trials running at that moment are retried when the snapshot is imported.

    Returns:
        ``(step, file, trials)`` for each snapshot written.
    """
    from ermrl.storage import write_snapshot

    out = []
    for step in steps:
        if step.stage != "evolve":
            continue
        with _study(exp.storage, step.study_name) as study:
            if study is None:
                continue
            path = snapshot_path(exp, step)
            path.parent.mkdir(parents=True, exist_ok=True)
            doc = write_snapshot(study, path)
            out.append((step, path, len(doc["trials"])))
    return out


def import_snapshots(exp: ExperimentFile, steps: Sequence[Step]) -> list[tuple[Step, Path, int]]:
    """Import the snapshot of every evolution study the storage does not hold yet.

    Returns:
        ``(step, file, trials)`` for each study imported.

    Raises:
        ExperimentError: a snapshot that cannot be imported (one line).
    """
    from ermrl.storage import (
        LockTimeout,
        SnapshotError,
        StorageError,
        StudyExists,
        import_snapshot,
    )

    out = []
    for step in steps:
        if step.stage != "evolve":
            continue
        path = snapshot_path(exp, step)
        if not path.exists():
            continue
        with _study(exp.storage, step.study_name) as study:
            if study is not None:
                continue
        try:
            result = import_snapshot(path, exp.storage, step.study_name)
        except (SnapshotError, StudyExists, StorageError, LockTimeout) as err:
            raise ExperimentError(f"{path}: cannot import ({err})") from None
        out.append((step, path, len(result.study.get_trials(deepcopy=False))))
    return out


def _run_folders(root: Path) -> list[Path]:
    """The finished run folders (``agents/<agent>/seed_<s>/`` with a ``result.json``) under root."""
    from ermrl.analysis._results import RUNS_DIR

    return sorted(p.parent for p in root.glob(f"{RUNS_DIR}/*/seed_*/result.json"))


def _copy_run(src: Path, dest: Path, limit: int) -> bool:
    """Copy a run folder's plain files, ``result.json`` (which marks a run finished) last.

    Nothing is copied (``False``) when one of them is over ``limit`` bytes: a run is carried
    whole or not at all.
    """
    files = [
        f
        for f in sorted(src.iterdir())
        if f.is_file() and f.suffix.lower() in _PLAIN and not f.name.startswith(".")
    ]
    if any(f.stat().st_size > limit for f in files):
        return False
    for f in sorted(files, key=lambda f: f.name == "result.json"):
        _copy(f, dest / f.name)
    return True


def publish_finished_runs(exp: ExperimentFile, step: Step) -> int:
    """Publish the finished runs of a test step, finished or not, so another machine goes on.

    A test phase longer than one sitting is carried like an evolution: each finished run's
    plain files (``settings.json``, ``episodes.csv``, ``result.json``; never its model) are
    copied to ``<publish>/<task>/test/agents/<agent>/seed_<s>/``, with the phase's
    ``config.yaml`` (so a page of a phase still running names its selected trial), and
    `restore_finished_runs` puts them back on the next machine, where the test phase
    skips them as it skips any finished run (after checking their settings).

    Returns:
        The number of runs published (0 without ``publish`` in the file); a run with a file
        over `PUBLISH_MAX_BYTES` is not (it is trained again elsewhere).
    """
    if exp.publish is None or step.stage != "test" or step.folder is None:
        return 0
    from ermrl.analysis._results import KEPT_RECORD_DIR

    dest = exp.publish / step.label / step.stage
    # Written as the phase (or a piece of it) starts: its agents, its trial, its commands.
    records = [
        f
        for f in (step.folder / name for name in _PHASE_RECORDS)
        if f.is_file() and f.stat().st_size <= PUBLISH_MAX_BYTES
    ]
    for f in records:
        _copy(f, dest / f.name)
    return sum(
        _copy_run(run, dest / run.relative_to(step.folder), PUBLISH_MAX_BYTES)
        for run in _run_folders(step.folder)
        # A run trained again for its model, its published records not yet put back: the
        # published run stands.
        if not (run / KEPT_RECORD_DIR / "result.json").is_file()
    )


def restore_finished_runs(exp: ExperimentFile, step: Step) -> tuple[int, list[tuple[str, int]]]:
    """Put a test step's published finished runs back in its folder where it lacks them.

    The runs whose models the report replays (``step.replayed``) are trained again, a
    published run having no model; their published records wait in the run folder's
    ``published-record/`` and replace the new training's as it ends, so the published result
    stays the result (the same settings and seed in another population layout can return
    another value: floating-point order).

    Returns:
        ``(restored, retrained)``: the number of runs restored, and the ``(agent, seed)``
        runs left to train again for the report's replay.
    """
    if exp.publish is None or step.stage != "test" or step.folder is None:
        return 0, []
    from ermrl.analysis._results import KEPT_RECORD_DIR

    source = exp.publish / step.label / step.stage
    if source.resolve() == step.folder.resolve():
        return 0, []
    _restore_phase_records(source, step.folder)
    restored, retrained = 0, []
    for run in _run_folders(source):
        rel = run.relative_to(source)
        target = step.folder / rel
        if (target / "result.json").exists():
            continue
        try:
            key = (run.parent.name, int(run.name.removeprefix("seed_")))
        except ValueError:
            continue
        if key in step.replayed:
            # Trained again for its model; its published records are kept aside and put back
            # as that training ends (ermrl.test_phase.keep_published_record).
            if _copy_run(run, target / KEPT_RECORD_DIR, PUBLISH_MAX_BYTES):
                retrained.append(key)
            continue
        restored += _copy_run(run, target, PUBLISH_MAX_BYTES)
    return restored, retrained


# The records of a test phase beside its runs, carried with them: config.yaml (its agents,
# seeds and selected trial) first, then command.txt (one line per piece that trained runs).
_PHASE_RECORDS = ("config.yaml", "command.txt")


def _restore_phase_records(source: Path, folder: Path) -> None:
    """Put a phase's published ``config.yaml`` and ``command.txt`` back in a folder that has
    no ``config.yaml``, so that the next piece adds to the phase's records (the test phase
    joins a piece's records to the folder's, ``ermrl.test_phase``) instead of starting them
    again: on a fresh machine, a piece's ``config.yaml`` and summary used to list that piece's
    agents and seeds alone, and its ``command.txt`` its own command.
    """
    if (folder / _PHASE_RECORDS[0]).exists() or not (source / _PHASE_RECORDS[0]).is_file():
        return
    for name in reversed(_PHASE_RECORDS):  # config.yaml, which marks them restored, last
        if (source / name).is_file():
            _copy(source / name, folder / name)


def write_snapshot_files(exp: ExperimentFile, steps: Sequence[Step]) -> tuple[int, int]:
    """Everything ``ermrl run --snapshot`` writes: the evolution snapshots and the finished test
    runs. Returns ``(studies written, test runs published)``."""
    studies = write_snapshots(exp, steps)
    return len(studies), sum(publish_finished_runs(exp, step) for step in steps)


class PeriodicSnapshots:
    """Write `write_snapshot_files` every ``every`` seconds from a background thread.

    A sitting or a machine that ends (a time limit, a preemption, ``kill -9``) then loses at
    most ``every`` seconds of finished work, as long as the published folder is kept; a run
    that stops by itself (done, a failed stage, Ctrl-C or SIGTERM) writes one more snapshot
    on its way out, so it loses nothing finished. A snapshot that fails (a locked database, a
    full disk) is reported on ``stream`` in one line and tried again at the next tick; it
    never stops the run. Use it as a context manager.
    """

    def __init__(
        self, exp: ExperimentFile, steps: Sequence[Step], every: float, stream: Any = None
    ) -> None:
        import threading

        self.exp, self.steps, self.every = exp, list(steps), every
        self.stream = stream if stream is not None else sys.stderr
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="ermrl-snapshots", daemon=True)
        self.written = 0

    def __enter__(self) -> PeriodicSnapshots:
        if self.exp.publish is not None and self.every > 0:
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        started = self._thread.ident is not None
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=60)
        if started:  # the last tick can be up to ``every`` seconds old: one more, last one
            self._write("ermrl run: last snapshot skipped")

    def _loop(self) -> None:
        while not self._stop.wait(self.every):
            self._write(
                f"ermrl run: snapshot skipped, tried again in {format_duration(self.every)}"
            )

    def _write(self, failed: str) -> None:
        try:
            write_snapshot_files(self.exp, self.steps)
            self.written += 1
        except Exception as err:  # noqa: BLE001 - a snapshot must never stop the run
            print(f"{failed} ({type(err).__name__}: {err})", file=self.stream, flush=True)


def snapshot_status(exp: ExperimentFile, step: Step) -> tuple[float, str] | None:
    """For a study the storage lacks: the fraction of its budget left and what its snapshot holds.

    ``None``: no snapshot. The fraction counts the snapshot's finished trials as done, so the
    plan's "left" estimate of a run that continues from a snapshot is the part still to train.
    """
    import json

    path = snapshot_path(exp, step)
    if not path.exists():
        return None
    try:
        trials = json.loads(path.read_text())["trials"]
        done = sum(t.get("state") in ("COMPLETE", "PRUNED") for t in trials)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return 1.0, f"snapshot {path} unreadable"
    argv = step.argv
    n_trials = int(argv[argv.index("--n-trials") + 1]) if "--n-trials" in argv else 0
    left = max(n_trials - done, 0) / n_trials if n_trials else 1.0
    return left, f"snapshot {path}: {done} finished trials, imported when run"


def published_runs_status(exp: ExperimentFile, step: Step) -> tuple[float, str] | None:
    """For a test step on a machine that lacks some of its published finished runs: the
    fraction of its runs left to train and what the published folder holds.

    ``None``: nothing published that the run folder lacks. The runs the report replays
    (``step.replayed``) count as left: they are trained again for their models.
    """
    if exp.publish is None or step.stage != "test" or step.folder is None or not step.runs:
        return None
    from ermrl.analysis._results import RUNS_DIR

    def finished(base: Path, agent: str, seed: int) -> bool:
        return (base / RUNS_DIR / agent / f"seed_{seed}" / "result.json").is_file()

    source = exp.publish / step.label / step.stage
    here = sum(finished(step.folder, a, s) for a, s in step.runs)
    published = sum(
        not finished(step.folder, a, s) and (a, s) not in step.replayed and finished(source, a, s)
        for a, s in step.runs
    )
    if not published:
        return None
    total = len(step.runs)
    done = here + published
    return (total - done) / total, (
        f"{done}/{total} runs, {published} of them published in {source}, put back when run"
    )
