"""What an encoder is: its settings, its search space, its flags and agents, and its place in the
pipeline.

An encoder module subclasses [`Encoder`][ermrl.encoders.Encoder] and
[`ermrl.encoders`][ermrl.encoders] registers one instance (`ENCODERS`). Two places exist:

- ``"env"``: a frozen encoder (its weights never learn, as a reservoir's) wraps the
  vectorized environment, so every learner sees its states as observations
  ([`Encoder.wrap_env`][ermrl.encoders.Encoder.wrap_env]);
- ``"policy"``: a trainable encoder lives inside the learner's policy, where gradients reach it
  ([`Encoder.policy_kwargs`][ermrl.encoders.Encoder.policy_kwargs] gives the policy its feature
  extractor).

The outer loop never handles an encoder's own types: it samples a plain ``{name: value}`` dict
in the ranges of the encoder's space and [`Encoder.decode`][ermrl.encoders.Encoder.decode] turns it
into the encoder's settings. The rest of ermrl reads everything else it needs of an encoder from
this class: the ``ermrl evolve`` settings (`Encoder.settings`, schema fields), the search space they give
([`Encoder.space_from_args`][ermrl.encoders.Encoder.space_from_args]), the test-phase agents
(`Encoder.agents`), the checks made before a study is written
([`Encoder.check`][ermrl.encoders.Encoder.check]), how the report describes a study's encoder
([`Encoder.describe`][ermrl.encoders.Encoder.describe]) and which agents may share a population
([`Encoder.layout`][ermrl.encoders.Encoder.layout]).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from ermrl._config_base import AgentKind, Range, TaskConfig
from ermrl._schema import Spec, fields_of

if TYPE_CHECKING:
    from ermrl.encoders._settings import EncoderConfig

__all__ = ["Encoder"]


class Encoder:
    """An encoder of observations.

    Attributes:
        name: Registry name (``--encoder NAME``).
        description: One line for ``--help`` and the docs.
        place: ``"env"`` (frozen, wraps the env) or ``"policy"`` (trainable, in the policy).
        family: The family its reservoirs' settings hold
            ([`ermrl.config.EncoderConfig.family`][ermrl.config.EncoderConfig.family]), stored with
            a study's configuration: it tells which encoder reads them back. Unique in the registry.
        config_cls: Its settings dataclass (stored in a study's configuration):
            [`EncoderConfig`][ermrl.config.EncoderConfig] for an encoder whose settings are
            reservoirs and the shared encoding options.
        params_cls: The settings dataclass of one of its reservoirs (an element of
            ``EncoderConfig.reservoirs``).
        space_cls: Its search space dataclass: ``ranges()`` (name -> range of every evolved
            parameter), ``reference_params()``, ``contains()``, ``center_params()``,
            ``reservoirs_from()`` and ``default_reservoirs()`` (the unevolved reference).
        settings: Its own ``ermrl evolve`` settings: a frozen dataclass whose fields carry
            their option (`ermrl._schema.option`: help, bounds, metavar), which
            become options of ``ermrl evolve``, keys of an experiment file's ``evolve:`` and
            keywords of [`ermrl.evolve`][ermrl.runner.evolve]. Each sets the ``space_cls``
            field of its name (``<name>_range``: the [`Range`][ermrl.config.Range] ``<name>``,
            as ``LOW HIGH`` on its default's scale), or the one `space_fields` names. A setting
            two encoders declare alike is one option whose help joins theirs.
            ``--n-reservoirs``, ``--input-scaling-range``, ``--fixed-input-scaling`` and the
            encoding options are shared by every encoder.
        space_fields: Settings whose ``space_cls`` field is not named after them (setting ->
            field).
        agents: Its test-phase agents (name -> [`AgentKind`][ermrl.config.AgentKind], each of this
            encoder's family): one evolved and one unevolved agent at least.
        population: Whether the population backend's batched reservoir steps its reservoirs
            ([`ermrl.population`][ermrl.population]: it needs [`bank`][ermrl.encoders.Encoder.bank]
            and a bank with a `stack`); otherwise its studies train with the sb3 backend.
    """

    name: ClassVar[str]
    description: ClassVar[str]
    place: ClassVar[Literal["env", "policy"]] = "env"
    family: ClassVar[str]
    config_cls: ClassVar[type]
    params_cls: ClassVar[type]
    space_cls: ClassVar[type]
    settings: ClassVar[type | None] = None
    space_fields: ClassVar[Mapping[str, str]] = {}
    agents: ClassVar[Mapping[str, AgentKind]] = {}
    population: ClassVar[bool] = False

    def accepts(self, config: Any) -> bool:
        """Whether ``config`` is this encoder's settings (its class and its family)."""
        if not isinstance(config, self.config_cls):
            return False
        return getattr(config, "family", None) == self.family

    def decode(self, space: Any, params: Mapping[str, float], base: Any) -> Any:
        """The encoder settings of a sampled point: ``base`` with the evolved reservoirs."""
        return base.with_reservoirs(space.reservoirs_from(params))

    def wrap_env(self, venv: Any, config: Any, seed: int) -> Any:
        """Wrap ``venv`` so that it emits encoded observations (``place == "env"``)."""
        return venv

    def bank(self, config: Any, input_dim: int, seed: int) -> Any:
        """The bank (`StepBank`) that steps one agent's
        reservoirs on inputs of ``input_dim`` values, its random weights from ``seed``: what
        [`ReservoirVecEnv`][ermrl.encoders.ReservoirVecEnv] wraps an env with. An encoder that wraps
        the env in its own way ([`wrap_env`][ermrl.encoders.Encoder.wrap_env]) need not have one.

        Raises:
            NotImplementedError: this encoder has no bank.
        """
        raise NotImplementedError(f"--encoder {self.name} has no reservoir bank")

    def population_banks(
        self, configs: Sequence[Any], seeds: Sequence[int], input_dim: int
    ) -> list[Any]:
        """The banks of the agents of one population, in one layout (their
        `stack` steps them together); each agent's
        own [`bank`][ermrl.encoders.Encoder.bank] by default."""
        return [self.bank(c, input_dim, s) for c, s in zip(configs, seeds)]

    def policy_kwargs(self, config: Any) -> dict[str, Any]:
        """``policy_kwargs`` entries that put the encoder in the policy (``place == "policy"``)."""
        return {}

    def setting_specs(self) -> tuple[Spec, ...]:
        """Its `settings`' fields, as the schema reads them."""
        return () if self.settings is None else fields_of(self.settings)

    def space_from_args(self, args: Any) -> Any:
        """The search space that the options of ``ermrl evolve`` give (parsed, or the
        validated options of a file or a call): the shared ``n_reservoirs`` and input scaling,
        and each of its `settings` into its space field (one left at ``None`` keeps the
        space's default).

        Raises:
            ConfigError: a bad value (the space's own checks).
        """
        fields = {f.name: f for f in dataclasses.fields(self.space_cls)}
        kwargs: dict[str, Any] = {}
        if "n_reservoirs" in fields:
            kwargs["n_reservoirs"] = args.n_reservoirs
        if "input_scaling" in fields:
            fixed = getattr(args, "fixed_input_scaling", None)
            low, high = args.input_scaling_range
            kwargs["input_scaling"] = None if fixed is not None else Range(float(low), float(high))
            kwargs["fixed_input_scaling"] = 1.0 if fixed is None else fixed
        for spec in self.setting_specs():
            name = self.space_fields.get(spec.name, spec.name.removesuffix("_range"))
            value = getattr(args, spec.name, None)
            if value is None:
                continue
            default = fields[name].default
            if isinstance(default, Range):  # LOW HIGH, on the default's scale (and type)
                value = dataclasses.replace(default, low=value[0], high=value[1])
            kwargs[name] = value
        return self.space_cls(**kwargs)

    def check(self, task: TaskConfig, config: EncoderConfig, space: Any) -> None:
        """Refuse, before a study or a run folder is written, what this encoder could only
        refuse once a trial runs on ``task`` (a size that depends on the task's input).

        Raises:
            ConfigError: one line saying what to change.
        """

    def describe(self, space: Any) -> str:
        """What the study's encoder is, in a few words (a row of the report's study table)."""
        units = getattr(space, "units", None)
        if units is None:
            return f"{space.n_reservoirs} x {self.name}"
        return f"{space.n_reservoirs} x {units} units"

    def layout(self, params: Any) -> Hashable:
        """What fixes the layout of what the policy sees of one reservoir (agents of a
        population share it): its state width by default."""
        return int(params.state_dim)
