"""``hebbian``: a leaky-integrator network whose readout learns by a reward-modulated Hebbian rule.

The agent of cristianocapone/RL_ML_class (https://github.com/cristianocapone/RL_ML_class,
``network.py`` and its Ant-v4 notebooks), with that code's bugs fixed (issue 16): no backprop,
no replay, one online pass. ``N`` leaky units with
per-unit time constants ``tau`` spread log-uniformly over ``[tau_min, tau_max]``::

    alpha = exp(-dt / tau)
    h_t   = alpha * h_{t-1} + (1 - alpha) * tanh(J h_{t-1} + J_in o_t + b)
    mu_t  = tanh(J_out h_t),   a_t = mu_t + sigma xi_t,   xi_t ~ N(0, I)
    e_t   = lambda e_{t-1} + ((a_t - mu_t) * (1 - mu_t^2)) h_t^T / sigma^2
    G    += (r_t - b_t) e_t                      (each step once)
    J_out <- J_out + Adam(G / n_envs - l2 J_out)  (at each episode end, or every k steps); G <- 0

With a critic (``baseline: critic`` or ``td``) the rule is actor-critic with eligibility traces
(Sutton and Barto 2018, section 13.6): a linear critic ``V(h) = w.h + c`` learns by TD(lambda_c)
(``critic_lambda``), and the actor's trace decays by ``gamma lambda`` and is modulated by the
TD error::

    delta_t = r_t + gamma V(h_{t+1}) - V(h_t)      (V = 0 after a terminal step)
    e_t     = gamma lambda e_{t-1} + ((a_t - mu_t) * (1 - mu_t^2)) h_t^T / sigma^2
    G      += delta_t e_t

so step ``k``'s eligibility is weighted by ``sum_{t>=k} (gamma lambda)^(t-k) delta_t``, the
GAE(lambda) advantage of step ``k``: with ``lambda = 1`` it is ``G_k - V(h_k)``, an unbiased
policy gradient for any critic. Two earlier rules were biased and are gone: ``critic`` used
``G += (r_t - V(h_t)) e_t`` with a trace decaying by ``lambda``, whose terms
``psi_k V(h_t)``, ``t > k``, do not vanish in expectation (``h_t`` depends on ``a_k``), pushing
the policy towards low-value states; ``td`` decayed the trace by ``lambda`` alone, unbiased only
when ``lambda = gamma`` (``trace_decay`` is an evolved gene, so it rarely is). Both names now
run the same rule; ``critic`` is kept so that existing settings load.

Only ``J_out`` (and the critic) learn; ``J``, ``J_in`` and ``b`` are fixed.

Deviations from the original beyond its bugs (all deliberate):

- **tanh in the leaky dynamics, with the bias inside it.** The original's ``step_`` applies
  ``tanh`` only when called with ``if_tanh=True`` (its notebooks do), and that branch drops the
  external field ``h``; here ``tanh`` is always applied, to ``J h + J_in o + b``.
- **1/sigma^2 in the eligibility.** The original's trace is ``(a - mu)(1 - mu^2) h^T``, without
  the ``1 / sigma^2`` of the Gaussian score; here it is included, so the update is the policy
  gradient's estimate (Adam is nearly invariant to that constant scale, except through eps).
- **Adam's eps.** The original's ``Adam`` class defaults to ``epsilon = 1e-5``; here ``adam_eps``
  defaults to ``1e-8`` (Kingma and Ba's value, torch's default).
- **The accumulator.** The original added ``r e`` to its accumulator twice per step; here each
  step counts once.
- **The learning rate.** ``learning_rate`` defaults to 1e-4, the step the original's Adam uses
  on ``J_out``. A notebook head with ``learning_rate = 0.`` (which would train nothing) has been
  reported for one version of the original; it is not in the versions of ``code.ipynb`` and
  ``training_ant.ipynb`` read for ermrl, and ermrl does not copy it. The model
(`HebbianAgent`, numpy only) lives in
`ermrl.learners._hebbian_model`, imported when an agent is built. It is not an SB3 algorithm
but offers what ermrl uses of one: ``learn`` (with SB3 callbacks), ``predict`` (recurrent: the
state is ``h``), ``num_timesteps``, ``save`` (a plain ``.npz``: arrays and a JSON config, no
pickle) and ``policy`` (``state_dict`` of CPU tensors, ``load_state_dict``,
``set_training_mode``), so ``train_agent``, ``save_trained``/``load_policy``, evaluation and
replays take it unchanged.

Settings (``ermrl/data/hebbian.yml``): this learner's own keys (`HebbianLearner.own_keys`)
and two keys it shares with PPO, ``learning_rate`` (Adam's step on ``J_out``, default 1e-4) and
``gamma`` (the critic's discount). Any other PPO key is refused. Box actions follow the
equations above (clipped, then mapped onto the action bounds); Discrete actions use a softmax
readout ``p = softmax(J_out h)``, ``a ~ p``, with the softmax's score as eligibility,
``e_t = lambda e_{t-1} + (onehot(a_t) - p_t) h_t^T`` (``sigma`` unused). Other action spaces are
refused with a one-line [`ConfigError`][ermrl.config.ConfigError].
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import AgentKind, ConfigError, PPOConfig, Range
from ermrl.learners._base import Learner

__all__ = ["HebbianLearner", "BASELINES", "GENES", "REWARDS", "SHARED_KEYS"]

MAX_UNITS = 4096
# Baselines b_t: none (b = 0), a running mean of the reward, or a linear critic V(h) trained by
# TD(lambda): critic and td both modulate the actor's trace (decaying by gamma lambda) by the
# critic's TD error, actor-critic with eligibility traces (td is the name; critic is kept).
BASELINES = ("none", "mean", "critic", "td")
# The reward that modulates plasticity: the task's, or the torso's forward velocity
# info["x_velocity"] (the original's choice on Ant; MuJoCo locomotion tasks report it).
REWARDS = ("task", "x_velocity")
DTYPES = ("float64", "float32")
# PPO keys this learner reads too (with these defaults when the table does not set them).
SHARED_KEYS: Mapping[str, Any] = {"learning_rate": 1e-4, "gamma": 0.99}
# The evolvable genes (evolve --learner hebbian) and their default search ranges. Two are
# reparametrized so that a box is always valid and log scales fit: tau_ratio = tau_max / tau_min
# (>= 1, so tau_max >= tau_min) and trace_horizon = 1 / (1 - trace_decay) (the trace's time
# constant in steps: 2 -> lambda 0.5, 100 -> 0.99, 1000 -> 0.999). The rest are settings.
# The baseline is a categorical choice, fixed per study (--ppo baseline=...).
GENES: Mapping[str, Range] = {
    "spectral_radius": Range(0.05, 3.0),
    "input_scaling": Range(1e-3, 1.0),
    "bias_scaling": Range(0.0, 1.0, log=False),
    "tau_min": Range(1.0, 100.0),
    "tau_ratio": Range(1.0, 100.0),
    "sigma": Range(0.02, 1.0),
    "trace_horizon": Range(2.0, 1000.0),
    "learning_rate": Range(1e-6, 1e-2),
    "l2": Range(1e-6, 10.0),
}
# The largest trace horizon a trace decay of 1 (no decay) is read as.
_MAX_HORIZON = 1e6
# Keys read by ermrl itself, never an algorithm's.
_ERMRL_KEYS = {"n_envs", "normalize"}


def _number(
    key: str, value: Any, low: float, high: float = math.inf, *, open_low: bool = False
) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"hebbian {key} must be a finite number, got {value!r}")
    if (value <= low if open_low else value < low) or value > high:
        bound = f"{'>' if open_low else '>='} {low:g}" + (
            f" and <= {high:g}" if math.isfinite(high) else ""
        )
        raise ConfigError(f"hebbian {key} must be {bound}, got {value!r}")
    return float(value)


class HebbianLearner(Learner):
    """The ``hebbian`` learner: settings, their checks, and the agent's construction.

    Own keys (defaults from the original, see ``ermrl/data/hebbian.yml``): ``units`` (N),
    ``sigma`` (exploration noise), ``trace_decay`` (lambda), ``adam_betas``, ``adam_eps``,
    ``tau_min``/``tau_max``/``dt`` (same time unit; ms in the original), ``spectral_radius``
    (rho of ``J``), ``input_scaling`` (std of ``J_in``), ``bias_scaling`` (std of ``b``),
    ``readout_scaling`` (std of the initial ``J_out``), ``l2``, ``baseline`` (one of
    `BASELINES`), ``baseline_decay`` (of the running mean), ``critic_lr``,
    ``critic_lambda``, ``update_every`` (0: update at each episode end; k: every k steps),
    ``reward`` (one of `REWARDS`) and ``dtype``.
    """

    name = "hebbian"
    agents: ClassVar[Mapping[str, AgentKind]] = {
        "hebbian": AgentKind(
            "evolved", None,
            "the Hebbian learner with the selected evolved genes (evolve --learner hebbian studies)",
            None, "Hebbian (evolved genes)", "Hebbian\n(evolved)", "tab:cyan", family="hebbian",
        ),
        "random-hebbian": AgentKind(
            "unevolved", None,
            "the Hebbian learner with its default genes (the original's values; --learner hebbian "
            "studies)",
            None, "Hebbian (default genes)", "Hebbian\n(default)", "darkgoldenrod",
            family="hebbian",
        ),
    }  # fmt: skip
    description = "leaky-integrator network, readout learned by a reward-modulated Hebbian rule"
    table = "hebbian.yml"
    policy = "HebbianPolicy"
    recurrent = True
    own_keys = {
        "units": 500,
        "sigma": 0.25,
        "trace_decay": 0.99,
        "adam_betas": [0.9, 0.999],
        "adam_eps": 1e-8,
        "tau_min": 2.5,
        "tau_max": 10.0,
        "dt": 1.0,
        "spectral_radius": 0.95,
        "input_scaling": 0.01,
        "bias_scaling": 0.0,
        "readout_scaling": 0.01,
        "l2": 0.0,
        "baseline": "mean",
        "baseline_decay": 0.99,
        "critic_lr": 1e-3,
        "critic_lambda": 0.9,
        "update_every": 0,
        "reward": "task",
        "dtype": "float64",
    }

    genes = GENES
    shared_keys = SHARED_KEYS

    def decode_genes(self, values: Mapping[str, float]) -> dict[str, Any]:
        """Settings from genes: ``tau_max = tau_min * tau_ratio`` and
        ``trace_decay = 1 - 1 / trace_horizon``; the others are settings."""
        out: dict[str, Any] = {
            k: float(v) for k, v in values.items() if k not in ("tau_ratio", "trace_horizon")
        }
        if "tau_ratio" in values:
            out["tau_max"] = float(values["tau_min"]) * float(values["tau_ratio"])
        if "trace_horizon" in values:
            out["trace_decay"] = 1.0 - 1.0 / float(values["trace_horizon"])
        return out

    def gene_values(self, config: PPOConfig) -> dict[str, float]:
        get = self.option
        tau_min = float(get(config, "tau_min"))
        decay = float(get(config, "trace_decay"))
        derived = {
            "tau_ratio": float(get(config, "tau_max")) / tau_min,
            "trace_horizon": min(1.0 / (1.0 - decay), _MAX_HORIZON) if decay < 1 else _MAX_HORIZON,
        }
        return {k: derived[k] if k in derived else float(get(config, k)) for k in self.genes}

    def algorithm(self) -> type:
        from ermrl.learners._hebbian_model import HebbianAgent

        return HebbianAgent

    def check(self, config: PPOConfig) -> None:
        super().check(config)
        foreign = set(config.hyperparams) - set(self.own_keys) - set(SHARED_KEYS) - _ERMRL_KEYS
        if foreign:
            raise ConfigError(
                f"learner 'hebbian' does not take {', '.join(sorted(foreign))} (a setting of "
                "another learner)"
            )
        get = self.option
        units = get(config, "units")
        if isinstance(units, bool) or not isinstance(units, int) or not 1 <= units <= MAX_UNITS:
            raise ConfigError(
                f"hebbian units must be a whole number in [1, {MAX_UNITS}], got {units!r}"
            )
        _number("sigma", get(config, "sigma"), 0.0, open_low=True)
        _number("trace_decay", get(config, "trace_decay"), 0.0, 1.0)
        _number("learning_rate", get(config, "learning_rate"), 0.0, open_low=True)
        _number("gamma", get(config, "gamma"), 0.0, 1.0)
        betas = get(config, "adam_betas")
        if not isinstance(betas, (list, tuple)) or len(betas) != 2:
            raise ConfigError(f"hebbian adam_betas must be two numbers in [0, 1), got {betas!r}")
        for beta in betas:
            if _number("adam_betas", beta, 0.0, 1.0) >= 1.0:
                raise ConfigError(
                    f"hebbian adam_betas must be two numbers in [0, 1), got {betas!r}"
                )
        _number("adam_eps", get(config, "adam_eps"), 0.0, open_low=True)
        tau_min = _number("tau_min", get(config, "tau_min"), 0.0, open_low=True)
        tau_max = _number("tau_max", get(config, "tau_max"), 0.0, open_low=True)
        if tau_max < tau_min:
            raise ConfigError(f"hebbian tau_max ({tau_max:g}) must be >= tau_min ({tau_min:g})")
        _number("dt", get(config, "dt"), 0.0, open_low=True)
        for key in ("spectral_radius", "input_scaling", "bias_scaling", "readout_scaling", "l2"):
            _number(key, get(config, key), 0.0)
        for key, choices in (("baseline", BASELINES), ("reward", REWARDS), ("dtype", DTYPES)):
            if get(config, key) not in choices:
                raise ConfigError(
                    f"hebbian {key} must be one of {', '.join(choices)}, got {get(config, key)!r}"
                )
        decay = _number("baseline_decay", get(config, "baseline_decay"), 0.0, 1.0)
        if decay >= 1.0:
            raise ConfigError(f"hebbian baseline_decay must be < 1, got {decay!r}")
        _number("critic_lr", get(config, "critic_lr"), 0.0, open_low=True)
        _number("critic_lambda", get(config, "critic_lambda"), 0.0, 1.0)
        every = get(config, "update_every")
        if isinstance(every, bool) or not isinstance(every, int) or every < 0:
            raise ConfigError(
                f"hebbian update_every must be a whole number >= 0 (0: at episode ends), got {every!r}"
            )

    def kwargs(self, config: PPOConfig) -> dict[str, Any]:
        """The agent's settings (no PPO argument is passed on)."""
        return self.settings(config)

    def build(
        self,
        env: Any,
        config: PPOConfig,
        *,
        seed: int | None = None,
        device: str | None = None,
        tensorboard_log: str | None = None,
    ) -> Any:
        """A new, untrained Hebbian agent on ``env`` (numpy on the CPU: ``device`` is ignored, and
        so is ``tensorboard_log``: the agent logs nothing).

        Raises:
            ConfigError: a bad setting, or an action space that is neither Box nor Discrete.
        """
        from ermrl.learners._hebbian_model import HebbianAgent

        return HebbianAgent(env, self.settings(config), seed=seed)
