"""``ermrl scores``: measure random-policy episodic returns for the normalized fitness."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

from ermrl.cli._common import fail
from ermrl.config import ConfigError
from ermrl.runner._options import ArgumentParser, HelpFormatter, nonneg_int, positive_int

__all__ = ["build_scores_parser", "scores_main"]

DESCRIPTION = textwrap.dedent(
    """\
    Measure the mean episodic return of a uniformly random policy (R_random) on each env and
    write it into the reference table that the generalization fitness
    (R - R_random) / (R_target - R_random) reads.

    The table written is --out, by default scores.csv in the current folder; a new file starts
    as a copy of the packaged table (ermrl/data/scores.csv), which is never changed. Pass it to
    evolve-generalization with --scores. Other rows and the target columns are kept; a new row
    of a known MuJoCo body gets its documented targets.

    example:
      ermrl scores --env-ids Ant-v5 Swimmer-v5 --episodes 100
    """
)


def build_scores_parser(prog: str = "ermrl scores") -> ArgumentParser:
    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    tasks = parser.add_mutually_exclusive_group(required=True)
    tasks.add_argument("--env-ids", nargs="+", metavar="ENV_ID", help="gymnasium env ids")
    tasks.add_argument(
        "--suite", default=None, help="every env of a suite (see ermrl/data/suites.yml)"
    )
    parser.add_argument(
        "--suites-file", default=None, metavar="YAML", help="extra suite definitions"
    )
    parser.add_argument(
        "--env-version", default=None, metavar="vN", help="with --suite: use this env version (v4)"
    )
    parser.add_argument(
        "--episodes", type=positive_int, default=100, help="random-policy episodes per env"
    )
    parser.add_argument("--seed", type=nonneg_int, default=0, help="seed of the env and actions")
    parser.add_argument(
        "--out",
        default="scores.csv",
        metavar="CSV",
        help="table to update; a new file starts from the packaged ermrl/data/scores.csv",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    return parser


def scores_main(argv: Sequence[str] | None = None, prog: str = "ermrl scores") -> int:
    """Entry point of ``ermrl scores``."""
    from ermrl.envs import UnknownEnvError, check_env_id, get_suite
    from ermrl.search._scores import (
        format_scores,
        load_scores,
        measure_random_returns,
        scores_path,
        update_scores,
    )

    parser = build_scores_parser(prog)
    args = parser.parse_args(argv)
    try:
        if args.suite is not None:
            env_ids = get_suite(args.suite, args.suites_file, env_version=args.env_version).env_ids
        else:
            if args.env_version is not None:
                raise ConfigError("--env-version applies to --suite only; write the ids in full")
            env_ids = tuple(dict.fromkeys(args.env_ids))
        for env_id in env_ids:
            check_env_id(env_id)
        path = scores_path(args.out)
        if path.exists() and not path.is_file():
            raise ConfigError(f"{path} is not a file")
        if path.exists():
            load_scores(path)  # a damaged table is refused before minutes of episodes
    except (ConfigError, UnknownEnvError) as err:
        fail(prog, str(err))
    if not args.quiet:
        print(
            f"random-policy returns, {args.episodes} episodes per env -> {path} "
            f"(use it with --scores {path})",
            flush=True,
        )
    rows = []
    for env_id in env_ids:
        score = measure_random_returns(env_id, args.episodes, args.seed)
        try:
            table = update_scores([score], path, start_from=scores_path())
        except OSError as err:
            fail(
                prog,
                f"cannot write {path}: {err.strerror or err}; the score of {env_id} was not "
                "recorded and the table is whole (pass --out FILE)",
            )
        except ConfigError as err:  # the table was changed by someone else since it was checked
            fail(prog, str(err))
        rows.append(table[env_id])
        if not args.quiet:
            print(
                f"{env_id}: {score.mean:.4g} +- {score.std:.3g} over {len(score.returns)} episodes "
                f"(mean length {score.mean_length:.0f}, {score.wall_seconds:.0f}s)",
                flush=True,
            )
    if not args.quiet:
        print(format_scores(rows))
        missing = [r.env_id for r in rows if r.target is None]
        if missing:
            print(
                f"note: no target return for {', '.join(missing)}; fill the target and "
                f"target_source columns of {path} before using them in evolve-generalization"
            )
    return 0
