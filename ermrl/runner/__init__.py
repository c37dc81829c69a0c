"""Run experiments and their stages from Python: what ``ermrl run`` and the commands do.

An experiment file (``experiments/*.yaml``) composes ermrl's commands: evolution, re-evaluation,
the test phase and the report (see docs/experiments.md). [`Experiment`][ermrl.runner.Experiment]
loads one, plans it and runs its unfinished stages, exactly as ``ermrl run FILE`` does;
[`evolve`][ermrl.runner.evolve], [`test`][ermrl.runner.test] and [`report`][ermrl.runner.report] run
one stage each, as ``ermrl evolve``, ``ermrl test`` and ``ermrl report`` do. The same names are
exported at the package root (``ermrl.Experiment``, ``ermrl.evolve``, ...).

Examples:
    >>> import ermrl
    >>> exp = ermrl.Experiment.load("experiments/demo.yaml")
    >>> exp.plan()[0].stage
    'evolve'
"""

from ermrl.runner._experiment import (
    ExperimentError,
    ExperimentFile,
    Step,
    experiment_plan,
    load_experiment,
)
from ermrl.runner._objects import Candidate, Evolution
from ermrl.runner._results import Experiment, ExperimentResult, PlanStep, TaskResult
from ermrl.runner._run import (
    StageFailed,
    StageInterrupted,
    plan_lines,
    run_experiment,
    run_plan,
    stage_argv,
)
from ermrl.runner._stages import (
    EvolveResult,
    NothingToReport,
    TestResult,
    evolve,
    evolve_config,
    report,
    test,
)

__all__ = [
    "Candidate",
    "Evolution",
    "EvolveResult",
    "Experiment",
    "ExperimentError",
    "ExperimentFile",
    "ExperimentResult",
    "NothingToReport",
    "PlanStep",
    "StageFailed",
    "StageInterrupted",
    "Step",
    "TaskResult",
    "TestResult",
    "evolve",
    "evolve_config",
    "experiment_plan",
    "load_experiment",
    "plan_lines",
    "report",
    "run_experiment",
    "run_plan",
    "stage_argv",
    "test",
]
