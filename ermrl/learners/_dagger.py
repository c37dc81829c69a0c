"""``dagger``: DAgger from an expert that sees the full state (Ross, Gordon and Bagnell, 2011).

Iteration ``i`` rolls out the mixture policy for ``steps_per_iteration`` env steps: at each
step, with probability ``beta_i`` the expert's action is executed, otherwise the imitator's;
every visited state is labelled with the expert's action on its raw full observation. The
imitator (an MLP on the learner's observation: masked by ``--observe``, maybe
reservoir-encoded) is then refit, ``epochs`` passes of mean squared error, on every label so
far. ``beta_schedule``: ``linear``, ``beta_i = max(0, 1 - i / beta_iterations)``, or
``inverse``, ``beta_i = 1 / (1 + i)``. Unlike Panjete/mujocoagents, which labelled a state with
the learner's own action with probability ``1 - beta``, labels always come from the expert.

The budget (``--training-steps``) counts every env step of the rollouts, whoever acted; the
expert's own training steps are in its ``expert.json``. The pieces are in
`ermrl.learners._imitation`, the agent in `ermrl.learners._dagger_model`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

from ermrl.config import AgentKind, ConfigError, PPOConfig
from ermrl.learners._bc import ImitationLearner, _whole

__all__ = ["DAggerLearner"]


class DAggerLearner(ImitationLearner):
    """``dagger``. Own keys: ``expert`` (required), ``steps_per_iteration``, ``beta_schedule``
    (``linear`` | ``inverse``), ``beta_iterations`` (K of the linear schedule),
    ``hidden_sizes``, ``epochs`` (passes over the aggregated data after each iteration)."""

    name = "dagger"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "dagger": AgentKind(
            "none", None,
            "DAgger on the raw (masked) observation; its expert sees the full state "
            "(--for-learner dagger expert=DIR)",
            "dagger", "DAgger (raw observation)", "DAgger", "navy", default=False,
        ),
    }  # fmt: skip
    description = "DAgger: an MLP trained on expert labels of its own rollouts (--ppo expert=DIR)"
    table = "dagger.yml"
    own_keys = {
        **ImitationLearner.common_keys,
        "steps_per_iteration": 1000,
        "beta_schedule": "linear",
        "beta_iterations": 10,
    }

    def check(self, config: PPOConfig) -> None:
        from ermrl.learners._imitation import BETA_SCHEDULES

        super().check(config)
        _whole("dagger", "steps_per_iteration", self.option(config, "steps_per_iteration"), 1)
        _whole("dagger", "beta_iterations", self.option(config, "beta_iterations"), 1)
        schedule = self.option(config, "beta_schedule")
        if schedule not in BETA_SCHEDULES:
            raise ConfigError(
                f"dagger beta_schedule must be one of {', '.join(BETA_SCHEDULES)}, got {schedule!r}"
            )
