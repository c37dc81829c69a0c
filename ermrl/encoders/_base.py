"""What an encoder is: its parameters, its search space, and its place in the pipeline.

An encoder module subclasses :class:`Encoder` and :mod:`ermrl.encoders` registers one instance
(:data:`~ermrl.encoders.ENCODERS`). Two places exist:

- ``"env"``: a frozen encoder (its weights never learn, as a reservoir's) wraps the
  vectorized environment, so every learner sees its states as observations
  (:meth:`Encoder.wrap_env`);
- ``"policy"``: a trainable encoder lives inside the learner's policy, where gradients reach it
  (:meth:`Encoder.policy_kwargs` gives the policy its feature extractor).

The outer loop never handles an encoder's own types: it samples a plain ``{name: value}`` dict
in the ranges of the encoder's space and :meth:`Encoder.decode` turns it into the encoder's
settings.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar, Literal

__all__ = ["Encoder"]


class Encoder:
    """An encoder of observations.

    Attributes:
        name: Registry name.
        description: One line for the docs.
        place: ``"env"`` (frozen, wraps the env) or ``"policy"`` (trainable, in the policy).
        family: The reservoirs' family its settings hold (:attr:`ermrl.config.EncoderConfig.family`);
            two encoders may share a settings class and differ by family.
        config_cls: Its settings dataclass (stored in a study's configuration).
        space_cls: Its search space dataclass: ``ranges()`` (name -> range of every evolved
            parameter), ``reference_params()``, ``contains()`` and ``center_params()``.
    """

    name: ClassVar[str]
    description: ClassVar[str]
    place: ClassVar[Literal["env", "policy"]] = "env"
    family: ClassVar[str | None] = None
    config_cls: ClassVar[type]
    space_cls: ClassVar[type]

    def accepts(self, config: Any) -> bool:
        """Whether ``config`` is this encoder's settings (its class and, if set, its family)."""
        if not isinstance(config, self.config_cls):
            return False
        return self.family is None or getattr(config, "family", None) == self.family

    def decode(self, space: Any, params: Mapping[str, float], base: Any) -> Any:
        """The encoder settings of a sampled point: ``base`` with the evolved parameters."""
        raise NotImplementedError

    def wrap_env(self, venv: Any, config: Any, seed: int) -> Any:
        """Wrap ``venv`` so that it emits encoded observations (``place == "env"``)."""
        return venv

    def policy_kwargs(self, config: Any) -> dict[str, Any]:
        """``policy_kwargs`` entries that put the encoder in the policy (``place == "policy"``)."""
        return {}
