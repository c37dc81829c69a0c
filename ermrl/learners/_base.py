"""What a learner is: the inner loop's algorithm, its settings, and how its agents are built.

A learner module subclasses [`Learner`][ermrl.learners.Learner], sets its class attributes and
overrides the hooks that differ from plain PPO; [`ermrl.learners`][ermrl.learners] registers one
instance of it. Everything else (the CLI's ``--learner`` choices, the test phase's agents, the
report's labels, replays) reads the registry, so a new learner is one module and one registry line.

Settings are an [`PPOConfig`][ermrl.config.PPOConfig] (``n_envs``, ``normalize``, the algorithm's
keyword arguments in ``hyperparams``, and ``learner``: the registry name). They resolve as SB3
defaults < the learner's YAML table (``default`` block, then the env id's block) < ``--ppo``
overrides ([`ermrl.agents.resolve_ppo_config`][ermrl.agents.resolve_ppo_config]).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar

from ermrl.config import AgentKind, ConfigError, LearnerSpace, PPOConfig, Range

__all__ = ["Learner"]


class Learner:
    """An inner learner: an on-policy SB3-style algorithm, its policy and its settings table.

    Attributes:
        name: Registry name (``--learner``, the agents' names).
        description: One line for ``--help`` and the docs.
        table: The packaged YAML table of settings keyed by env id (``ermrl/data/<table>``).
        policy: The policy class name passed to the algorithm (``"MlpPolicy"``).
        own_keys: Settings this learner reads itself, with their defaults; they are never passed
            to the algorithm, and other learners refuse them.
        recurrent: The policy carries a hidden state between steps (``predict`` needs
            ``state`` and ``episode_start``; SB3's ``evaluate_policy`` passes them).
        shared_keys: PPO keys a learner that is not an SB3 algorithm reads too, with its own
            defaults (the Hebbian learner's ``learning_rate`` and ``gamma``).
        checks_itself: Settings whose values [`check`][ermrl.learners.Learner.check] validates,
            skipped by the shared PPO range checks (SAC's ``ent_coef`` may be ``"auto"``).
        genes: The settings evolution may shape (``evolve --learner NAME``), gene name ->
            default search range; empty: the learner has no genes and a study evolves an
            encoder for it. [`decode_genes`][ermrl.learners.Learner.decode_genes] turns genes into
            settings.
        agents: The test-phase agents this learner brings (name ->
            [`AgentKind`][ermrl.config.AgentKind]): the learner on the raw observation (``sac``), or
            its own evolved and default genes (``hebbian``, ``random-hebbian``). Declared on the
            class that brings them; a subclass declares its own (it never inherits them). The agents
            on an encoder come with the encoder (`ermrl.encoders.Encoder.agents`);
            `ermrl.learners.AGENT_KINDS` lists both.
    """

    name: ClassVar[str]
    description: ClassVar[str]
    table: ClassVar[str] = "ppo.yml"
    policy: ClassVar[str] = "MlpPolicy"
    own_keys: ClassVar[Mapping[str, Any]] = {}
    recurrent: ClassVar[bool] = False
    genes: ClassVar[Mapping[str, Range]] = {}
    shared_keys: ClassVar[Mapping[str, Any]] = {}
    checks_itself: ClassVar[frozenset[str]] = frozenset()
    agents: ClassVar[Mapping[str, AgentKind]] = {}

    def algorithm(self) -> type:
        """The algorithm class (imported lazily: torch is slow to import)."""
        from stable_baselines3 import PPO

        return PPO

    def option(self, config: PPOConfig, key: str) -> Any:
        """One of this learner's own settings (``own_keys``) or of the PPO keys it shares
        (``shared_keys``), or its default."""
        if key in self.shared_keys:
            return config.hyperparams.get(key, self.shared_keys[key])
        return config.hyperparams.get(key, self.own_keys[key])

    def settings(self, config: PPOConfig) -> dict[str, Any]:
        """Every own and shared setting of an agent that is not an SB3 algorithm, checked.

        Raises:
            ConfigError: a bad value, with a one-line reason.
        """
        self.check(config)
        return {key: self.option(config, key) for key in (*self.own_keys, *self.shared_keys)}

    def check(self, config: PPOConfig) -> None:
        """Refuse settings of another learner (e.g. ``frame_stack`` given to plain PPO).

        Raises:
            ConfigError: with a one-line reason.
        """
        from ermrl.learners import LEARNERS

        foreign = {
            key
            for other in LEARNERS.values()
            if other.name != self.name
            for key in other.own_keys
            if key not in self.own_keys and key in config.hyperparams
        }
        if foreign:
            raise ConfigError(
                f"learner {self.name!r} does not take {', '.join(sorted(foreign))} "
                "(a setting of another learner)"
            )

    def kwargs(self, config: PPOConfig) -> dict[str, Any]:
        """The algorithm's keyword arguments (``lin_X`` strings become schedules)."""
        from ermrl.learners._kwargs import ppo_kwargs

        return {k: v for k, v in ppo_kwargs(config).items() if k not in self.own_keys}

    def wrap_env(self, venv: Any, config: PPOConfig) -> Any:
        """The learner's own wrappers, outermost (after the encoder and ``VecNormalize``)."""
        return venv

    def build(
        self,
        env: Any,
        config: PPOConfig,
        *,
        seed: int | None = None,
        device: str | None = None,
        tensorboard_log: str | None = None,
    ) -> Any:
        """A new, untrained agent on ``env`` (already wrapped by
        [`wrap_env`][ermrl.learners.Learner.wrap_env])."""
        self.check(config)
        return self.algorithm()(
            self.policy,
            env,
            seed=seed,
            device=device or config.device,
            verbose=0,
            tensorboard_log=tensorboard_log,
            **self.kwargs(config),
        )

    # -- evolvable genes ---------------------------------------------------------------------

    def decode_genes(self, values: Mapping[str, float]) -> dict[str, Any]:
        """The settings a point of the gene space stands for (default: genes are settings)."""
        return dict(values)

    def gene_values(self, config: PPOConfig) -> dict[str, float]:
        """The genes of ``config``'s settings: the inverse of
        [`decode_genes`][ermrl.learners.Learner.decode_genes]."""
        return {name: float(self.option(config, name)) for name in self.genes}

    def gene_space(
        self, config: PPOConfig, ranges: Mapping[str, Range] | None = None
    ) -> LearnerSpace:
        """The study's search space of this learner's genes, whose reference is ``config``.

        Args:
            config: The study's settings of this learner (the unevolved reference).
            ranges: Other ranges for some genes (``--gene NAME=LOW:HIGH``).

        Raises:
            ConfigError: the learner has no genes, or ``ranges`` names another gene.
        """
        if not self.genes:
            raise ConfigError(
                f"learner {self.name!r} has no genes to evolve; a study evolves its encoder "
                "(--encoder)"
            )
        unknown = sorted(set(ranges or {}) - set(self.genes))
        if unknown:
            raise ConfigError(
                f"learner {self.name!r} has no gene {', '.join(unknown)}; its genes: "
                f"{', '.join(self.genes)}"
            )
        self.check(config)
        space = LearnerSpace(self.name, {**self.genes, **(ranges or {})}, self.gene_values(config))
        for end in ("low", "high"):  # a range the learner would refuse fails here, not mid-study
            self.with_genes(config, {n: getattr(r, end) for n, r in space.genes.items()})
        return space

    def with_genes(self, config: PPOConfig, values: Mapping[str, float]) -> PPOConfig:
        """``config`` with the settings of a point of the gene space, checked.

        Raises:
            ConfigError: the genes decode to a setting the learner refuses.
        """
        hyperparams = {**config.hyperparams, **self.decode_genes(values)}
        out = dataclasses.replace(config, hyperparams=hyperparams)
        self.check(out)
        return out
