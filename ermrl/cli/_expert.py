"""``ermrl expert``: train and evaluate experts for imitation (BC, DAgger)."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import textwrap
from collections.abc import Sequence
from pathlib import Path

from ermrl._progress import PROGRESS_MODES, Progress
from ermrl.cli._common import EXIT_INTERRUPTED, fail, progress_mode
from ermrl.runner._options import (
    PROGRESS_DEFAULT_HELP,
    ArgumentParser,
    HelpFormatter,
    nonneg_int,
    positive_int,
)

__all__ = ["build_expert_parser", "expert_main"]

DESCRIPTION = textwrap.dedent(
    """\
    Train an expert (an SB3 policy of the sac or ppo learner, on the task's full observation)
    and evaluate it. The expert folder holds plain files only: expert.json (settings, evaluation
    returns, versions), policy.pt (tensors, read with torch.load(weights_only=True)) and, when
    the settings use normalize, vecnormalize.json. Nothing is pickled.

    examples:
      ermrl expert train --env-id Pendulum-v1 --algo sac --steps 5000 --out experts/pendulum
      ermrl expert train --env-id Hopper-v5 --algo sac --steps 1000000 --out experts/hopper
      ermrl expert eval --expert experts/hopper --episodes 20 --out hopper_eval.csv
    """
)

TRAIN_DESCRIPTION = textwrap.dedent(
    """\
    Train an expert with ermrl's inner loop: the learner's settings come from its table
    (ermrl/data/sac.yml or ppo.yml, rl-baselines3-zoo's), then --ppo overrides. After training,
    the deterministic policy runs --n-eval-episodes episodes (seeded from --seed); their return
    is printed and recorded in expert.json. The folder is written under a temporary name and
    renamed when complete: an interrupted run leaves no half-written expert.

    examples:
      ermrl expert train --env-id Pendulum-v1 --steps 5000 --out experts/pendulum
      ermrl expert train --env-id Hopper-v5 --algo sac --steps 1000000 --out experts/hopper
      ermrl expert train --env-id Pendulum-v1 --algo ppo --steps 100000 --out experts/pend-ppo \\
          --ppo normalize=true
    """
)

EVAL_DESCRIPTION = textwrap.dedent(
    """\
    Run deterministic episodes of an expert on its task's full observation. With --seed equal
    to the training seed (the default) and as many episodes, it reproduces the return recorded
    at training.

    examples:
      ermrl expert eval --expert experts/pendulum
      ermrl expert eval --expert experts/hopper --episodes 20 --seed 7 --out hopper_eval.json
    """
)


def build_expert_parser(prog: str = "ermrl expert") -> ArgumentParser:
    from ermrl.experts import expert_algos

    parser = ArgumentParser(prog=prog, description=DESCRIPTION, formatter_class=HelpFormatter)
    sub = parser.add_subparsers(dest="command", metavar="{train,eval}", required=True)
    train = sub.add_parser(
        "train",
        help="train an expert and record its evaluation return",
        description=TRAIN_DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    train.add_argument("--env-id", required=True, help="gymnasium id (Hopper-v5, Pendulum-v1...)")
    train.add_argument("--algo", choices=expert_algos(), default="sac", help="learner")
    train.add_argument("--steps", type=positive_int, required=True, help="training env steps")
    train.add_argument("--out", required=True, help="expert folder to write")
    train.add_argument("--seed", type=nonneg_int, default=0, help="seed of envs and agent")
    train.add_argument(
        "--ppo",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="learner settings over its table (values read as YAML: learning_starts=1000, "
        "normalize=true, policy_kwargs='{net_arch: [64, 64]}')",
    )
    train.add_argument(
        "--n-eval-episodes", type=positive_int, default=10, help="evaluation episodes"
    )
    train.add_argument(
        "--overwrite", action="store_true", help="replace an expert already in --out"
    )
    train.add_argument(
        "--progress",
        choices=PROGRESS_MODES,
        default=None,
        help="bar: a live bar with the rate (from the first step: start-up excluded), ETA and "
        "recent return; lines: the same as a line every tenth of the steps or 30 s; none: no "
        f"progress ({PROGRESS_DEFAULT_HELP})",
    )
    train.add_argument(
        "--quiet", action="store_true", help="no output but errors (--progress none, no start line)"
    )
    evaluate = sub.add_parser(
        "eval",
        help="evaluate an expert",
        description=EVAL_DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    evaluate.add_argument("--expert", required=True, help="expert folder")
    evaluate.add_argument("--episodes", type=positive_int, default=10, help="episodes to run")
    evaluate.add_argument(
        "--seed", type=nonneg_int, default=None, help="evaluation seed (default: training seed)"
    )
    evaluate.add_argument(
        "--out", default=None, help="write per-episode returns to this .csv or .json file"
    )
    evaluate.add_argument("--quiet", action="store_true", help="no summary line")
    return parser


def _train(args: argparse.Namespace, prog: str, argv: Sequence[str]) -> int:
    from ermrl.agents import TrainingDiverged, parse_overrides
    from ermrl.config import ConfigError
    from ermrl.envs import UnknownEnvError
    from ermrl.experts import check_expert_out, train_expert

    try:
        overrides = parse_overrides(args.ppo, args.algo)
        check_expert_out(args.out, args.overwrite)
    except (ConfigError, FileExistsError) as err:
        fail(prog, str(err))

    mode = "none" if args.quiet else progress_mode(args)
    display = Progress(f"{args.algo} expert on {args.env_id}", args.steps, mode=mode)
    if not args.quiet:
        print(
            f"training a {args.algo} expert on {args.env_id} for {args.steps} steps "
            f"(seed {args.seed}) into {args.out}",
            flush=True,
        )
    try:
        info = train_expert(
            args.env_id,
            args.algo,
            steps=args.steps,
            out=args.out,
            seed=args.seed,
            overrides=overrides,
            n_eval_episodes=args.n_eval_episodes,
            overwrite=args.overwrite,
            display=display,
            command=shlex.join(["ermrl", "expert", *argv]),
        )
    except (ConfigError, UnknownEnvError, FileExistsError) as err:
        fail(prog, str(err))
    except TrainingDiverged as err:
        fail(prog, str(err), code=1)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; no expert written to {args.out}", file=sys.stderr)
        return EXIT_INTERRUPTED
    print(
        f"{info.env_id} {info.algo} expert: eval return {info.eval_mean:.1f} ± "
        f"{info.eval_std:.1f} over {len(info.eval_returns)} episodes "
        f"({info.env_steps} steps, {info.wall_seconds:.0f} s); wrote {args.out}",
        flush=True,
    )
    return 0


def _write_returns(path: Path, returns: Sequence[float], lengths: Sequence[int]) -> None:
    from ermrl._io import write_atomic

    if path.suffix == ".json":
        text = json.dumps({"returns": list(returns), "lengths": list(lengths)}, indent=1) + "\n"
    else:
        rows = [f"{i},{r!r},{n}" for i, (r, n) in enumerate(zip(returns, lengths, strict=True))]
        text = "episode,return,length\n" + "\n".join(rows) + "\n"
    write_atomic(path, text)


def _eval(args: argparse.Namespace, prog: str) -> int:
    from ermrl.envs import UnknownEnvError
    from ermrl.experts import evaluate_expert, load_expert

    out = None if args.out is None else Path(args.out)
    if out is not None and out.suffix not in (".csv", ".json"):
        fail(prog, f"--out must end in .csv or .json, got {str(out)!r}")
    try:
        expert = load_expert(args.expert)
    except (FileNotFoundError, ValueError, UnknownEnvError) as err:
        fail(prog, str(err))
    seed = expert.info.seed if args.seed is None else args.seed
    try:
        result = evaluate_expert(expert, args.episodes, seed)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    if out is not None:
        _write_returns(out, result.returns, result.lengths)
    if not args.quiet:
        print(
            f"{expert.env_id} {expert.algo} expert: eval return {result.mean:.1f} ± "
            f"{result.std:.1f} over {len(result.returns)} episodes (seed {seed}; recorded at "
            f"training: {expert.info.eval_mean:.1f} ± {expert.info.eval_std:.1f})"
            + ("" if out is None else f"; wrote {out}"),
            flush=True,
        )
    return 0


def expert_main(argv: Sequence[str] | None = None, prog: str = "ermrl expert") -> int:
    """Entry point of ``ermrl expert``."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    args = build_expert_parser(prog).parse_args(args_list)
    if args.command == "train":
        return _train(args, f"{prog} train", args_list)
    return _eval(args, f"{prog} eval")
