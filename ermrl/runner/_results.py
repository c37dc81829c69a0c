"""What an experiment plans and what it produced, as plain objects for Python callers."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from ermrl.runner._experiment import ExperimentFile, Step, experiment_plan, load_experiment
from ermrl.runner._run import DEFAULT_SNAPSHOT_EVERY, run_experiment, step_status

if TYPE_CHECKING:
    import pandas as pd

    from ermrl._progress import ProgressMode

__all__ = [
    "Experiment",
    "ExperimentResult",
    "PlanStep",
    "TaskResult",
    "experiment_result",
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


def experiment_result(exp: ExperimentFile, steps: Sequence[Step]) -> ExperimentResult:
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


@dataclass(frozen=True)
class Experiment(ExperimentFile):
    """An experiment file (variant applied), to plan, run and read back from Python.

    Its fields are those of the parsed file ([`ExperimentFile`][ermrl.runner.ExperimentFile]:
    ``name``, ``out``, ``storage``, ``stages``, ...); the plan and the stages read those, and
    this class only adds what a Python caller does with them.
    """

    @classmethod
    def load(cls, path: str | Path, variant: str | None = None) -> Experiment:
        """Read an experiment file and apply a variant
        ([`load_experiment`][ermrl.runner.load_experiment]).

        Args:
            path: The YAML file. Its folders (``out``, ``storage``, ``publish``) are relative
                to the working directory, as for ``ermrl run``.
            variant: A key of its ``variants`` (e.g. ``"quick"``); its results go to
                ``<out>/<variant>``. ``None``: the file as written.

        Returns:
            The experiment.

        Raises:
            ExperimentError: An unreadable file, an unknown key (with the nearest valid one),
                a wrong type or an unknown variant, in one line naming the file.

        Examples:
            >>> import ermrl
            >>> exp = ermrl.Experiment.load("experiments/demo.yaml")
            >>> exp.name, str(exp.out)
            ('demo', 'runs/demo')
        """
        file = load_experiment(path, variant)
        return cls(**{f.name: getattr(file, f.name) for f in dataclasses.fields(file)})

    def plan(self, tasks: Sequence[str] | None = None) -> list[PlanStep]:
        """Every step ``run`` would take, checked, with what is done (nothing is written).

        The same plan as ``ermrl run FILE --dry-run``: each stage's options are parsed by its
        command's own parser, and a study already in the storage must match the file.

        Args:
            tasks: Only these tasks (for a generalization experiment: these test tasks); a
                task the file does not list runs with the file's settings.

        Returns:
            One [`PlanStep`][ermrl.runner.PlanStep] per command, in the order they run.

        Raises:
            ExperimentError: A key or value the commands refuse, or a study that contradicts
                the file (one line).
        """
        out = []
        for step in experiment_plan(self, tasks=tasks, build_agents=False):
            done, _, text = step_status(self, step)
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

    def run(
        self,
        stages: Sequence[str] | None = None,
        tasks: Sequence[str] | None = None,
        progress: ProgressMode = "none",
        quiet: bool = True,
        *,
        tensorboard: str | Path | None = None,
        snapshot_every: float = DEFAULT_SNAPSHOT_EVERY,
        stream: TextIO | None = None,
    ) -> ExperimentResult:
        """Run the unfinished stages, exactly as ``ermrl run FILE`` does, and return the results.

        Finished stages are skipped and an interrupted one resumes (the study and the run
        folders are the state). Each stage runs its ``ermrl`` command in this process; with
        ``quiet=False`` the plan and each stage's equivalent command line are printed.

        Args:
            stages: Only these stages (``evolve``, ``reevaluate``, ``test``, ``report``;
                default: all, in order).
            tasks: Only these tasks (for a generalization experiment: these test tasks).
            progress: ``"bar"``, ``"lines"`` or ``"none"`` inside the evolve and test stages.
            quiet: No plan, no stage lines, and ``--quiet`` for every stage's command.
            tensorboard: Also log training curves for TensorBoard under this folder (the
                evolve and test stages then train with the sb3 backend).
            snapshot_every: With ``publish:`` in the file, write the snapshot every this many
                seconds while it runs (0: never).
            stream: Where the plan and the stage lines go (default ``sys.stdout``).

        Returns:
            The results per task: study, selected trial, test summary, report.

        Raises:
            ExperimentError: The file cannot run (one line), or its folder cannot be written.
            StageFailed: A stage's command stopped with an error (its own line is on stderr);
                run again to resume.
            KeyboardInterrupt: Ctrl-C during a stage (finished trials and runs are kept).

        Examples:
            >>> result = ermrl.Experiment.load("experiments/demo.yaml").run()
            >>> result["Pendulum-v1"].trial, result["Pendulum-v1"].summary
        """
        steps = run_experiment(
            self,
            stages=stages,
            tasks=tasks,
            progress=progress,
            tensorboard=None if tensorboard is None else str(tensorboard),
            snapshot_every=snapshot_every,
            quiet=quiet,
            quiet_stages=quiet,
            stream=stream or sys.stdout,
        )
        return experiment_result(self, steps)

    def result(self, tasks: Sequence[str] | None = None) -> ExperimentResult:
        """What the experiment's results folder holds now, without running anything.

        Args:
            tasks: Only these tasks.

        Raises:
            ExperimentError: The file no longer matches its studies (see
                [`plan`][ermrl.runner.Experiment.plan]).
        """
        return experiment_result(self, experiment_plan(self, tasks=tasks, build_agents=False))
