"""``rtu-ppo``: real-time PPO with a layer of recurrent trace units trained by exact RTRL.

Elelimy et al., "Real-Time Recurrent Learning using Trace Units in Reinforcement Learning"
(NeurIPS 2024; official JAX code esraaelelimy/rtus). The network is
``obs -> Dense(64) -> tanh -> linear RTU(d_rec) -> ReLU``, shared, then an actor head
(``Dense(64) -> tanh -> action distribution``) and a critic head (``Dense(64) -> tanh -> value``).
The RTU layer, its exact RTRL step and the algorithm (`RTUPPO`, an
SB3 ``OnPolicyAlgorithm``) live in `ermrl.learners._rtu`, imported only when an agent is
built: importing the learner registry stays free of torch.

Real-time PPO, as in the paper:

- every stored transition keeps its carry (the RTU state and RTRL traces as they were before
  that step); carries reset to zero at episode starts and otherwise run on across rollouts;
- minibatches are single steps, each recomputed from its stored carry with the current
  parameters: one RTU step whose backward gives the recurrent parameters their full RTRL
  gradient (and the layers below the one-step gradient);
- ``stale_gradient`` (default ``true``): the stored carries are never recomputed. With
  ``false``, the whole rollout is re-scanned with the new parameters after each epoch (from the
  rollout's first carry, resetting at episode starts) to recompute every stored carry; the
  advantages stay the rollout's (the official ``stale_target: true``);
- the loss is SB3's PPO (clipped surrogate, value loss, entropy, advantage normalisation, GAE
  with truncated episodes bootstrapped through ``terminal_observation``, gradient clipping,
  Adam with eps 1e-5).

**Memory: the traces are stored, not recomputed.** Each transition stores its carry in float32:
``2 d_rec d_in + 6 d_rec`` numbers (the ``W₂`` traces follow exactly from the ``W₁`` ones, see
`ermrl.learners._rtu`), 25,728 numbers (~103 kB) at ``d_rec`` 192 and ``d_in`` 64, so a
2048-step rollout holds ~211 MB of carries (the paper's layout, with all four weight traces,
would take ~410 MB). Measured on Pendulum-v1 with the default settings, the process's peak
resident memory grows by ~230 MB over one 2048-step rollout and its update. Recomputing the
carries instead would cost a sequential re-scan of the rollout before every epoch; storing is
what ``stale_gradient: true`` (the default) needs anyway. Speed on the same task (one torch
thread, a shared 2-core CPU): ~600 env steps/s with stale gradients, ~330 with
``stale_gradient: false`` (three re-scans per update).

Settings: ``ermrl/data/rtu_ppo.yml`` (the paper's ant_p configuration in its ``default`` block)
and this learner's own keys ``d_rec`` (RTU units, default 192) and ``stale_gradient``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import AgentKind, ConfigError, PPOConfig
from ermrl.learners._base import Learner

__all__ = ["RTUPPOLearner"]

MAX_D_REC = 4096


class RTUPPOLearner(Learner):
    name = "rtu-ppo"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "rtu-ppo": AgentKind(
            "none", None,
            "PPO with recurrent trace units learned online by RTRL (real-time PPO): learned memory",
            "rtu-ppo", "RTU-PPO (learned RTU)", "RTU-PPO", "tab:olive", default=False,
        ),
    }  # fmt: skip
    description = "real-time PPO, linear recurrent trace units trained by exact RTRL (d_rec=n)"
    table = "rtu_ppo.yml"
    recurrent = True
    own_keys = {"d_rec": 192, "stale_gradient": True}

    def algorithm(self) -> type:
        from ermrl.learners._rtu import RTUPPO

        return RTUPPO

    def check(self, config: PPOConfig) -> None:
        super().check(config)
        d_rec = self.option(config, "d_rec")
        if isinstance(d_rec, bool) or not isinstance(d_rec, int) or not 1 <= d_rec <= MAX_D_REC:
            raise ConfigError(f"d_rec must be a whole number in [1, {MAX_D_REC}], got {d_rec!r}")
        stale = self.option(config, "stale_gradient")
        if not isinstance(stale, bool):
            raise ConfigError(f"stale_gradient must be true or false, got {stale!r}")

    def kwargs(self, config: PPOConfig) -> dict[str, Any]:
        kwargs = super().kwargs(config)
        policy_kwargs = dict(kwargs.get("policy_kwargs") or {})
        policy_kwargs["d_rec"] = self.option(config, "d_rec")
        kwargs["policy_kwargs"] = policy_kwargs
        kwargs["stale_gradient"] = self.option(config, "stale_gradient")
        return kwargs
