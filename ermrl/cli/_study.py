"""``ermrl study``: create, list, show, export, import, delete studies, fail stale trials,
repair journals.

Before a SLURM array starts many workers on one storage, create the study once with
``ermrl study create`` (same options as ``ermrl evolve``): the configuration is checked before
any job is queued, and no worker races on a fresh database.

``ermrl study export --out X.json`` writes the whole study (and its re-evaluation study) as a
plain JSON snapshot, and ``ermrl study import --snapshot X.json`` restores it in another storage,
so that an evolution resumes on another machine (`ermrl.storage._snapshot`).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ermrl._code import describe_code, mixed_code
from ermrl._io import write_atomic
from ermrl._text import plural
from ermrl.cli._common import fail, quiet_libraries
from ermrl.runner._options import (
    ArgumentParser,
    HelpFormatter,
    add_storage_args,
    nonneg_int,
    storage_arg,
    study_name_arg,
)
from ermrl.storage._summary import (
    STATES,
    best_trial_or_none,
    stored_budget,
    study_summary,
    trial_counts,
    worker_budgets,
    worker_label,
)

__all__ = ["build_study_parser", "study_main", "parse_duration"]

DESCRIPTION = textwrap.dedent(
    """\
    Manage the studies of a storage (sqlite:///file.db, postgresql://..., mysql://...,
    journal:///file.log or file.log, redis://host:port).

    examples:
      ermrl study create --storage postgresql://me@db/ermrl --study-name pendulum \\
          --env-id Pendulum-v1 --observe positions --n-trials 500 --training-steps 300000
      ermrl study list --storage sqlite:///ermrl.db
      ermrl study show --storage sqlite:///ermrl.db --study-name pendulum
      ermrl study export --storage sqlite:///ermrl.db --study-name pendulum --out trials.parquet
      ermrl study export --storage sqlite:///ermrl.db --study-name pendulum --out pendulum.json
      ermrl study import --storage sqlite:///other.db --snapshot pendulum.json
      ermrl study fail-stale --storage studies.log --study-name pendulum --older-than 2h
      ermrl study delete --storage sqlite:///ermrl.db --study-name pendulum --yes
      ermrl study repair --storage studies.log
      ermrl study repair --storage "redis://localhost:6379/0?prefix=ermrl"
    """
)

_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def parse_duration(text: str) -> float:
    """Seconds in ``90``, ``90s``, ``30m``, ``2h`` or ``1.5d``.

    Raises:
        argparse.ArgumentTypeError: not a positive duration.
    """
    match = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*([smhd]?)\s*", text.lower())
    if not match:
        raise argparse.ArgumentTypeError(f"{text!r} is not a duration such as 90s, 30m, 2h or 1d")
    seconds = float(match.group(1)) * _UNITS[match.group(2) or "s"]
    if seconds <= 0:
        raise argparse.ArgumentTypeError(f"duration must be positive, got {text}")
    return seconds


def _study_parser(sub: Any, name: str, help_: str, *, study_required: bool = True) -> Any:
    parser = sub.add_parser(name, help=help_, description=help_, formatter_class=HelpFormatter)
    add_storage_args(parser, study_required=study_required)
    return parser


def build_study_parser(prog: str = "ermrl study") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    sub = parser.add_subparsers(dest="action", metavar="ACTION", parser_class=ArgumentParser)
    sub.required = True

    from ermrl.runner._parsers import add_problem_args, add_search_args

    create = sub.add_parser(
        "create",
        help="create the schema and a study before workers start (takes ermrl evolve's options)",
        description="Create the storage's schema and the study, once, before many workers "
        "start. With --env-id (and any other ermrl evolve option) the configuration is checked "
        "and stored, so every worker must match it; without, the first worker stores its own.",
        formatter_class=HelpFormatter,
    )
    create.add_argument("--env-id", default=None, help="gymnasium env id (stores a configuration)")
    add_problem_args(create, multi_task=True)
    add_search_args(create)

    listing = sub.add_parser(
        "list", help="studies of a storage with trial counts", formatter_class=HelpFormatter
    )
    add_storage_args(listing, study_required=False)

    show = _study_parser(sub, "show", "best trial, trials by state, workers, running trials")
    show.add_argument("--json", action="store_true", help="print one JSON document")

    export = _study_parser(
        sub,
        "export",
        "all trials with params and user attributes (.csv, .parquet, .jsonl), or the whole "
        "study as a JSON snapshot (.json) that 'ermrl study import' restores in another storage",
    )
    export.add_argument(
        "--out",
        required=True,
        help="output file: .csv, .parquet, .jsonl (the same table as JSON lines, one record "
        "per trial, for jq or pandas.read_json(lines=True)), .json (snapshot: every trial, "
        "attribute and "
        "distribution, the CMA-ES state, and the study's re-evaluation study), or - for CSV on "
        "stdout",
    )

    imp = sub.add_parser(
        "import",
        help="create a study (and its re-evaluation study) from a JSON snapshot of 'export'",
        description="Create the study of a snapshot written by 'ermrl study export --out "
        "X.json', with its trial numbers, states, parameters, attributes and CMA-ES state, so "
        "that 'ermrl evolve' resumes it here. A trial that was running at export is imported "
        "as FAIL and queued again with the same parameters. A study of that name that is "
        "already there is refused, unless it is identical (then nothing is done).",
        formatter_class=HelpFormatter,
    )
    imp.add_argument(
        "--storage", type=storage_arg, required=True, help="target storage URL (as for evolve)"
    )
    imp.add_argument(
        "--snapshot", required=True, metavar="FILE.json", help="a snapshot from export"
    )
    imp.add_argument(
        "--study-name",
        type=study_name_arg,
        default=None,
        help="import under this name (default: the exported name; <name>.reeval follows)",
    )
    imp.add_argument(
        "--max-retry",
        type=nonneg_int,
        default=3,
        help="retries of one trial at most, for trials running at export; 0: only fail them",
    )

    delete = _study_parser(sub, "delete", "delete a study and all its trials")
    delete.add_argument("--yes", action="store_true", help="really delete (required)")

    stale = _study_parser(
        sub,
        "fail-stale",
        "mark FAIL the RUNNING trials with no sign of life, and retry them (journal storages "
        "have no automatic heartbeat check without running workers)",
    )
    stale.add_argument(
        "--older-than",
        type=parse_duration,
        required=True,
        metavar="DURATION",
        help="no heartbeat (or, without heartbeats, no start) for this long: 90s, 30m, 2h, 1d",
    )
    stale.add_argument(
        "--max-retry",
        type=nonneg_int,
        default=3,
        help="retries of one trial at most (a WAITING copy with the same parameters); 0: none",
    )
    stale.add_argument(
        "--dry-run", action="store_true", help="only list the trials that would be failed"
    )

    repair = sub.add_parser(
        "repair",
        help="set aside the unreadable records of a journal (file or Redis) and renumber it, "
        "or roll back a SQLite database's unfinished transaction",
        description="A journal holds records no command can read when a write was cut short "
        "(full disk, dead node), when another process appended a partial record, or when a "
        "record is garbage: every command then stops with one line that asks for this repair.\n"
        "Journal file: what cannot be read, anywhere in the file, is moved to "
        "FILE.torn-<UTC time>; a readable record is never removed (records glued together on "
        "one line are split onto lines of their own, a valid record glued onto a partial one "
        "is kept); every other record stays, in order (workers also do this when they open "
        "the journal to write).\n"
        "Redis journal: unreadable records are moved to the hash PREFIX:torn-<UTC time>, the "
        "others are renumbered without gaps and PREFIX:log_number is set to the last of them "
        "(a log_number ahead of the stored records made every command wait forever).\n"
        "SQLite: a transaction a writer left unfinished (killed mid-write: a hot DB-journal file) "
        "is rolled back, as every command does when it opens the database, then the database is "
        "checked (PRAGMA quick_check).\n"
        "One line says how many records were set aside, and where.",
        formatter_class=HelpFormatter,
    )
    repair.add_argument(
        "--storage",
        type=storage_arg,
        required=True,
        help="journal:///file.log, file.log, redis://host:port[/db][?prefix=NAME] or "
        "sqlite:///file.db",
    )
    return parser


def _budget_text(budget: int | None, worker_budgets: dict[int, int]) -> str:
    """``"9"``, or ``"1,10"`` when workers and the stored configuration disagree."""
    values = sorted({*worker_budgets, *([budget] if budget else [])})
    return ",".join(map(str, values)) if values else "?"


def _fmt(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.6g}"


def _open_study(args: argparse.Namespace, prog: str, mode: str = "read") -> Any:
    from ermrl.storage import StorageError, StudyNotFound, load_study

    try:
        return load_study(args.study_name, args.storage, mode=mode)  # type: ignore[arg-type]
    except (StorageError, StudyNotFound) as err:
        fail(prog, str(err))


def _create(args: argparse.Namespace, prog: str) -> int:
    from ermrl.config import ConfigError
    from ermrl.envs import UnknownEnvError, UnsupportedObserveError
    from ermrl.runner._resolve import config_from_args
    from ermrl.search import create_or_resume_study
    from ermrl.storage import LockTimeout, StorageError

    if not args.study_name:
        fail(prog, "--study-name is required")
    config = None
    if args.env_id is not None:
        try:
            config = config_from_args(args)
        except (ConfigError, UnknownEnvError, UnsupportedObserveError) as err:
            fail(prog, str(err))
    try:
        from ermrl.storage import load_study

        existed = True
        try:
            load_study(args.study_name, args.storage)
        except (LookupError, StorageError):  # no such study, or no such file yet
            existed = False
        study = create_or_resume_study(
            config,
            args.storage,
            args.study_name,
            command=" ".join(["ermrl", "study", "create", *sys.argv[1:]]),
        )
    except (ConfigError, StorageError, LockTimeout) as err:
        fail(prog, str(err))
    n = len(study.get_trials(deepcopy=False))
    what = "exists" if existed else "created"
    configured = "with" if "ermrl_config" in study.user_attrs else "without"
    if not args.quiet:
        print(
            f"study {args.study_name!r} {what} in {args.storage} ({plural(n, 'trial')}, {configured} an "
            "ermrl configuration)"
        )
    return 0


def _list(args: argparse.Namespace, prog: str) -> int:
    import optuna

    from ermrl.storage import StorageError, open_storage, printable_name

    try:
        storage = open_storage(args.storage, mode="read")
    except StorageError as err:
        fail(prog, str(err))
    studies = storage.get_all_studies()
    if not studies:
        print(f"no study in {args.storage}")
        return 0
    rows = []
    for frozen in studies:
        study = optuna.load_study(study_name=frozen.study_name, storage=storage)
        trials = study.get_trials(deepcopy=False)
        counts = trial_counts(trials)
        best = best_trial_or_none(study)
        budget = stored_budget(study)
        rows.append(
            [
                printable_name(frozen.study_name),
                str(study.user_attrs.get("ermrl_kind", "-")),
                f"{counts['COMPLETE'] + counts['PRUNED']}/"
                + _budget_text(budget, worker_budgets(trials)),
                *(str(counts[s]) for s in STATES),
                _fmt(best.value if best else None),
            ]
        )
    header = ["study", "kind", "done/budget", *(s.lower() for s in STATES), "best"]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, *rows]:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip())
    return 0


def _code_line(code: list[dict[str, Any]]) -> str:
    """The code versions of a study's trials in one line (`study_summary`'s ``code``)."""
    versions = [(record, record["trials"]) for record in code]
    mixed = mixed_code(versions)
    if mixed is not None:
        return f"code: {mixed}"
    if not versions:
        return "code: not recorded"
    return f"code: {describe_code(versions[0][0])} (every trial)"


def _show(args: argparse.Namespace, prog: str) -> int:
    study = _open_study(args, prog)
    info = study_summary(study)
    info["reevaluation"] = study.user_attrs.get("ermrl_reevaluation")
    if args.json:
        print(json.dumps(info, indent=2, default=str))
        return 0
    counts = info["counts"]
    done = counts["COMPLETE"] + counts["PRUNED"]
    task = (
        f"{info['env_id']} [{info['observe']}], {info['training_steps']} steps"
        if info["env_id"]
        else "no ermrl configuration yet"
    )
    print(f"study {info['study']!r} ({info['kind'] or '-'}): {task}")
    budgets = info["worker_budgets"]
    agreed = _budget_text(info["budget"], budgets)
    print(
        (f"trials: {done}/{agreed} done | " if "," not in agreed else f"trials: {done} done | ")
        + ", ".join(f"{counts[s]} {s.lower()}" for s in STATES)
        + f" | {info['retried']} retries"
    )
    if "," in agreed:  # workers were started with different --n-trials
        used = ", ".join(f"{n} ({k} trial{'s' if k != 1 else ''})" for n, k in budgets.items())
        stored = info["budget"] or "none"
        print(
            f"budgets differ: workers ran with --n-trials {used or '-'}; "
            f"the study's configuration says {stored}"
        )
    print(_code_line(info["code"]))
    best = info["best"]
    if best is None:
        print("best: none yet")
    else:
        params = " ".join(f"{k}={v:.4g}" for k, v in best["params"].items())
        print(
            f"best: trial {best['number']} fitness {_fmt(best['value'])} ({params}) by {best['worker']}"
        )
    reevaluation = info["reevaluation"]
    if isinstance(reevaluation, dict) and reevaluation.get("candidates"):
        from ermrl.search import stale_ranking

        seeds = reevaluation["seeds"]
        state = "" if reevaluation.get("complete") else " (incomplete)"
        stale = stale_ranking(study)
        if stale is not None:
            state += f" (stale, not used by ermrl test: {stale})"
        print(
            f"re-evaluated{state} on {plural(len(seeds), 'fresh seed')} x "
            f"{reevaluation['training_steps']} steps (study {reevaluation['study']!r}):"
        )
        for row in reevaluation["candidates"]:
            tag = " (reference)" if row.get("reference") else ""
            params = " ".join(f"{k}={v:.4g}" for k, v in row["params"].items())
            value = (
                f"FAILED ({row.get('fail_reason')})" if row.get("failed") else _fmt(row["fitness"])
            )
            print(
                f"  trial {row['trial']}{tag}: {value} "
                f"[evolution {_fmt(row['evolution_fitness'])}] ({params})"
            )
    if info["workers"]:
        print(f"workers ({len(info['workers'])}):")
        for worker, n in info["workers"].items():
            print(f"  {worker}: {plural(n, 'trial')}")
    for run in info["running"]:
        print(
            f"running: trial {run['number']} on {run['worker']}, "
            f"last heartbeat {run['seconds_since_heartbeat']:.0f} s ago"
        )
    return 0


def _export(args: argparse.Namespace, prog: str) -> int:
    study = _open_study(args, prog)
    out = Path(args.out)
    suffix = out.suffix.lower()
    if args.out != "-" and suffix not in (".csv", ".parquet", ".jsonl", ".json"):
        fail(prog, f"--out must end in .csv, .parquet, .jsonl or .json, got {args.out!r}")
    if args.out != "-" and not out.parent.exists():
        fail(prog, f"directory {out.parent} does not exist")
    if suffix == ".json":
        from ermrl.storage import snapshot_counts, write_snapshot

        try:
            doc = write_snapshot(study, out)
        except OSError as err:
            fail(prog, _write_error(out, err))
        counts = ", ".join(
            f"{name!r} ({plural(n, 'trial')})" for name, n in snapshot_counts(doc).items()
        )
        print(f"wrote a snapshot of {counts} to {out}")
        return 0
    from ermrl.analysis import trials_table

    frame = trials_table(study)
    if args.out == "-":
        frame.to_csv(sys.stdout, index=False)
        return 0
    # Built in memory, then written to a temporary name and renamed: a read-only folder or a
    # full disk leaves no partial file under --out (nor a previous export damaged).
    data: str | bytes
    if suffix == ".csv":
        data = frame.to_csv(index=False)
    elif suffix == ".jsonl":
        # ISO dates, not epoch milliseconds; NaN and NaT as null.
        data = frame.to_json(orient="records", lines=True, date_format="iso")
    else:
        try:
            data = frame.to_parquet(None, index=False)
        except ImportError as err:
            fail(prog, f"Parquet needs pyarrow ({err}); write .csv instead")
    try:
        write_atomic(out, data)
    except OSError as err:
        fail(prog, _write_error(out, err))
    print(f"wrote {plural(len(frame), 'trial')} of {args.study_name!r} to {out}")
    return 0


def _write_error(out: Path, err: OSError) -> str:
    """One line for an export that could not be written (read-only folder, full disk, ...)."""
    return (
        f"cannot write {out}: {err.strerror or err}; nothing was written (free space, or "
        "choose a writable --out)"
    )


def _import(args: argparse.Namespace, prog: str) -> int:
    from ermrl.config import ConfigError
    from ermrl.search import STUDY_CONFIG_ATTR, check_stored_env_ids
    from ermrl.storage import (
        LockTimeout,
        SnapshotError,
        StorageError,
        StudyExists,
        import_snapshot,
        read_snapshot,
    )

    try:
        snapshot = read_snapshot(args.snapshot)
        for part in (snapshot.study, *snapshot.related.values()):
            if STUDY_CONFIG_ATTR in part.user_attrs:  # never import a module it names
                where = f"{args.snapshot}: study {part.study_name!r} (its stored configuration)"
                check_stored_env_ids(part.user_attrs[STUDY_CONFIG_ATTR], where)
        result = import_snapshot(snapshot, args.storage, args.study_name, max_retry=args.max_retry)
    except (SnapshotError, StudyExists, StorageError, LockTimeout, ConfigError) as err:
        fail(prog, str(err))
    for name in result.created:
        print(
            f"imported study {name!r} ({plural(result.n_trials[name], 'trial')}) into {args.storage}"
        )
    for name in result.identical:
        print(f"study {name!r} in {args.storage} is identical to the snapshot: nothing to import")
    for name, number, retry in result.interrupted:
        then = f"retried as trial {retry}" if retry is not None else "not retried"
        print(f"trial {number} of {name!r} was running at export: imported as FAIL, {then}")
    return 0


def _delete(args: argparse.Namespace, prog: str) -> int:
    import optuna

    from ermrl.storage import storage_lock

    study = _open_study(args, prog, mode="write")
    n = len(study.get_trials(deepcopy=False))
    if not args.yes:
        fail(prog, f"study {args.study_name!r} has {plural(n, 'trial')}; pass --yes to delete it")
    with storage_lock(args.storage, args.study_name):
        optuna.delete_study(study_name=args.study_name, storage=study._storage)
    print(f"deleted study {args.study_name!r} ({plural(n, 'trial')}) from {args.storage}")
    return 0


def _fail_stale(args: argparse.Namespace, prog: str) -> int:
    from ermrl.storage import RetryStaleTrial, fail_stale, storage_lock

    study = _open_study(args, prog, mode="write")
    retry = RetryStaleTrial(args.max_retry) if args.max_retry > 0 else None
    with storage_lock(args.storage, args.study_name):
        done = fail_stale(study, args.older_than, retry=retry, dry_run=args.dry_run)
    verb = "would fail" if args.dry_run else "failed"
    for trial, retried in done:
        then = " and retry" if retried else ""
        print(f"{verb}{then} trial {trial.number} (worker {worker_label(trial)})")
    print(
        f"{len(done)} stale trial(s) older than {args.older_than:.0f} s in {args.study_name!r}"
        + (" (dry run)" if args.dry_run else "")
    )
    return 0


def _repair(args: argparse.Namespace, prog: str) -> int:
    from ermrl.storage import (
        JournalRepair,
        StorageError,
        parse_storage_url,
        repair_journal,
        repair_redis_journal,
        repair_sqlite,
    )

    try:
        spec = parse_storage_url(args.storage)
    except StorageError as err:
        fail(prog, str(err))
    if spec.kind == "sqlite":
        try:
            rolled_back = repair_sqlite(spec)
        except StorageError as err:
            fail(prog, str(err))
        print(
            f"{spec.path}: rolled back the transaction a writer left unfinished"
            if rolled_back
            else f"{spec.path}: intact, nothing to repair"
        )
        return 0
    if spec.kind not in ("journal", "redis"):
        fail(
            prog,
            f"{spec.kind} storages repair themselves (the server rolls back unfinished "
            f"transactions); only journals and SQLite files can be repaired ({args.storage})",
        )
    repair: JournalRepair | None
    if spec.kind == "redis":
        try:
            repair = repair_redis_journal(spec)
        except StorageError as err:
            fail(prog, str(err))
        where = args.storage
    else:
        path = spec.path
        assert path is not None, spec
        if not path.is_file() and not path.is_dir():
            fail(prog, f"no journal file {path}")
        try:
            repair = repair_journal(path)
        except StorageError as err:  # a directory, or not a journal: left untouched
            fail(prog, str(err))
        except OSError as err:
            fail(prog, f"cannot set aside the unreadable records of {path}: {err.strerror or err}")
        where = str(path)
    print(f"{where}: intact, nothing to repair" if repair is None else repair.describe())
    return 0


_ACTIONS = {
    "create": _create,
    "list": _list,
    "show": _show,
    "export": _export,
    "import": _import,
    "delete": _delete,
    "fail-stale": _fail_stale,
    "repair": _repair,
}


def study_main(argv: Sequence[str] | None = None, prog: str = "ermrl study") -> int:
    """Entry point of ``ermrl study``."""
    parser = build_study_parser(prog)
    quiet_libraries()
    args = parser.parse_args(argv)
    return _ACTIONS[args.action](args, f"{prog} {args.action}")
