"""What an experiment plans and what it produced, as plain objects for Python callers."""

from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from ermrl.runner._experiment import Experiment, Step, experiment_plan
from ermrl.runner._run import DEFAULT_SNAPSHOT_EVERY, run_experiment, step_status

if TYPE_CHECKING:
    import pandas as pd

    from ermrl._progress import ProgressMode

__all__ = [
    "ExperimentResult",
    "PlanStep",
    "TaskResult",
    "experiment_result",
    "plan_steps",
    "run_and_collect",
]


@dataclass(frozen=True)
class PlanStep:
    """One step of an experiment's plan, as ``ermrl run --dry-run`` prints it.

    Attributes:
        stage: ``evolve``, ``reevaluate``, ``test`` or ``report``.
        task: The task (env id) it is about; a generalization experiment's evolution names
            its task set (its suite, or the env ids joined by ``+``).
        command: The equivalent command line (``ermrl evolve ...``); a ``reevaluate`` step
            is run by the evolve command once the budget is spent.
        env_steps: Env steps it trains in all (0: none).
        seconds: Estimated wall seconds on 2 cores (``ermrl/data/throughput.yml``).
        done: Whether the storage or the folders say it is finished.
        status: What they say, in words (``"2/3 trials"``, ``"not started"``, ...).
        study_name: The study it reads or writes.
        folder: The folder it writes (test and report steps; ``None`` otherwise).
    """

    stage: str
    task: str
    command: str
    env_steps: int
    seconds: float
    done: bool
    status: str
    study_name: str
    folder: Path | None = None


@dataclass(frozen=True, eq=False)
class TaskResult:
    """The results of one task of an experiment (what exists of them so far).

    Attributes:
        task: The task (env id; for a generalization experiment, the test task).
        study_name: The evolution study.
        trial: The trial the test phase trained (``None``: no test phase yet).
        params: Its evolved parameters (``sr_0``, ``lr_0``, ...; empty without a test phase).
        summary: The test phase's ``summary.csv``: one row per agent, with the mean, std and
            IQM of the final returns (``None``: no test phase yet).
        test_folder: The test phase's folder (``None``: the file has no test stage).
        report: The report's ``report.md`` (``None``: not written).
    """

    task: str
    study_name: str
    trial: int | None
    params: dict[str, Any]
    summary: pd.DataFrame | None = field(repr=False)
    test_folder: Path | None
    report: Path | None


@dataclass(frozen=True, eq=False)
class ExperimentResult:
    """What an experiment holds in its results folder.

    Attributes:
        name: The experiment's name.
        out: Its results folder.
        tasks: ``{task: TaskResult}``, in the plan's order.

    Examples:
        >>> result = Experiment.load("experiments/demo.yaml").run()
        >>> result["Pendulum-v1"].summary[["agent", "final_return_mean"]]
    """

    name: str
    out: Path
    tasks: dict[str, TaskResult]

    def __getitem__(self, task: str) -> TaskResult:
        """The result of one task (raises ``KeyError`` naming the tasks there are)."""
        try:
            return self.tasks[task]
        except KeyError:
            raise KeyError(f"no task {task!r}; the tasks are {', '.join(self.tasks)}") from None

    def __iter__(self) -> Iterator[TaskResult]:
        return iter(self.tasks.values())

    @property
    def summary(self) -> pd.DataFrame:
        """Every task's test summary in one table, with a ``task`` column first (empty when
        no test phase has finished)."""
        import pandas as pd

        frames = [
            r.summary.assign(task=r.task)[["task", *r.summary.columns]]
            for r in self
            if r.summary is not None
        ]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=["task"])


def plan_steps(exp: Experiment, tasks: Sequence[str] | None = None) -> list[PlanStep]:
    """The plan of an experiment, checked as ``ermrl run --dry-run`` checks it.

    Args:
        exp: The experiment.
        tasks: Only these tasks (for a generalization experiment: these test tasks).

    Raises:
        ExperimentError: A key or value the commands refuse, or a study that contradicts the
            file (one line).
    """
    out = []
    for step in experiment_plan(exp, tasks=tasks, build_agents=False):
        done, _, text = step_status(exp, step)
        out.append(
            PlanStep(
                stage=step.stage,
                task=step.label,
                command=step.command_line,
                env_steps=step.env_steps,
                seconds=step.seconds,
                done=done,
                status=text,
                study_name=step.study_name,
                folder=step.folder,
            )
        )
    return out


def experiment_result(exp: Experiment, steps: Sequence[Step]) -> ExperimentResult:
    """The results the steps of an experiment wrote so far, task by task.

    Args:
        exp: The experiment.
        steps: Its plan ([`experiment_plan`][ermrl.runner.experiment_plan]).

    Raises:
        ermrl.analysis.RunFolderError: A test phase's ``config.yaml`` is damaged.
    """
    import pandas as pd

    from ermrl.analysis import load_run_config

    tasks: dict[str, TaskResult] = {}
    labels = dict.fromkeys(
        s.label
        for s in steps
        if s.stage == "test" or (s.stage == "evolve" and not exp.generalization)
    )
    for label in labels:
        own = {s.stage: s for s in steps if s.label == label}
        test, report = own.get("test"), own.get("report")
        trial, params, summary = None, {}, None
        folder = None if test is None else test.folder
        if folder is not None and (folder / "config.yaml").is_file():
            config = load_run_config(folder)
            trial, params = config.get("trial"), dict(config.get("params") or {})
        if folder is not None and (folder / "summary.csv").is_file():
            summary = pd.read_csv(folder / "summary.csv")
        markdown = None if report is None or report.folder is None else report.folder / "report.md"
        tasks[label] = TaskResult(
            task=label,
            study_name=(test or own["evolve"]).study_name,
            trial=trial,
            params=params,
            summary=summary,
            test_folder=folder,
            report=markdown if markdown is not None and markdown.is_file() else None,
        )
    return ExperimentResult(name=exp.name, out=exp.out, tasks=tasks)


def run_and_collect(
    exp: Experiment,
    *,
    stages: Sequence[str] | None = None,
    tasks: Sequence[str] | None = None,
    progress: ProgressMode = "none",
    quiet: bool = True,
    tensorboard: str | Path | None = None,
    snapshot_every: float = DEFAULT_SNAPSHOT_EVERY,
    stream: TextIO | None = None,
) -> ExperimentResult:
    """Run an experiment's unfinished stages as ``ermrl run`` does and read back its results.

    See [`ermrl.Experiment.run`][ermrl.runner.Experiment.run] for the arguments.
    """
    steps = run_experiment(
        exp,
        stages=stages,
        tasks=tasks,
        progress=progress,
        tensorboard=None if tensorboard is None else str(tensorboard),
        snapshot_every=snapshot_every,
        quiet=quiet,
        quiet_stages=quiet,
        stream=stream or sys.stdout,
    )
    return experiment_result(exp, steps)
