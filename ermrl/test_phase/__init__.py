"""The test phase: the selected reservoirs trained against baselines on new seeds.

This package was called ``ermrl.experiments`` before; that name still imports, with a
`DeprecationWarning` (experiment files are run by [`ermrl.runner`][ermrl.runner]).
"""

from ermrl.test_phase._prepare import (
    TestOptions,
    TestPhase,
    TestPlan,
    check_for_learner,
    parse_for_learner,
    prepare_test,
    run_in_folder,
)
from ermrl.test_phase._test_phase import (
    AGENT_KINDS,
    AGENTS,
    AgentKind,
    AgentSpec,
    Selection,
    TestSettings,
    agent_specs,
    aggregate,
    check_finished_runs,
    default_agents,
    default_test_seeds,
    describe_selection,
    learner_settings_for,
    run_comparison,
    run_settings,
    select_reservoirs,
    selection_metadata,
    settings_diff,
    study_agents,
    study_reservoirs,
)

__all__ = [
    "AGENTS",
    "AGENT_KINDS",
    "AgentKind",
    "AgentSpec",
    "Selection",
    "TestOptions",
    "TestPhase",
    "TestPlan",
    "TestSettings",
    "agent_specs",
    "aggregate",
    "check_finished_runs",
    "check_for_learner",
    "default_agents",
    "default_test_seeds",
    "describe_selection",
    "learner_settings_for",
    "parse_for_learner",
    "prepare_test",
    "run_comparison",
    "run_in_folder",
    "run_settings",
    "select_reservoirs",
    "selection_metadata",
    "settings_diff",
    "study_agents",
    "study_reservoirs",
]
