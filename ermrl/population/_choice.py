"""Which backend trains a run: the population backend wherever it applies, else SB3.

``--backend`` left out means the population backend trains PPO agents (on reservoir
states of any registered encoder, or on the raw observation) and the SB3 path, the reference
implementation, trains whatever it does not implement: another learner, PPO settings it lacks
(``target_kl``, some ``policy_kwargs``), a pruner (it reports no intermediate returns),
Weights & Biases logs, and envs whose spaces it does not step (observations other than a flat
``Box``, actions other than ``Box`` and ``Discrete``).
[`population_refusal`][ermrl.population.population_refusal] says why in one line, which the commands
print when they fall back.
"""

from __future__ import annotations

from ermrl.config import ConfigError, PPOConfig, TaskConfig

__all__ = ["choose_backend", "population_refusal"]

_HINT = "; use --backend sb3"


def _env_refusal(task: TaskConfig) -> str | None:
    """Why the population backend cannot step ``task``'s env (``None``: it can, or the env
    cannot be built here, which the run itself reports whatever the backend)."""
    from gymnasium import spaces

    from ermrl.envs import make_env

    try:
        env = make_env(task.env_id, task.observe)
    except Exception:  # noqa: BLE001 - reported by the checks and runs of either backend
        return None
    try:
        obs, act = env.observation_space, env.action_space
    finally:
        env.close()
    if not isinstance(obs, spaces.Box) or len(obs.shape) != 1:
        return f"the population backend needs flat Box observations, {task.env_id} has {obs}"
    if not isinstance(act, (spaces.Box, spaces.Discrete)):
        return f"the population backend steps Box and Discrete actions, {task.env_id} has {act}"
    return None


def population_refusal(
    ppo: PPOConfig,
    tasks: tuple[TaskConfig, ...] = (),
    *,
    pruner: str = "none",
    wandb: bool = False,
    encoder: str | None = None,
) -> str | None:
    """Why the population backend cannot train these runs as SB3 would, in one line.

    Args:
        ppo: The learner's settings (its ``backend`` is ignored).
        tasks: The envs the runs train on (their spaces are checked; none: not checked).
        pruner: The study's pruner (``"none"``: no pruning).
        wandb: The runs log to Weights & Biases (wandb's SB3 callback).
        encoder: The registered encoder the runs evolve (``None``: none, or not checked); one
            whose reservoirs the batched reservoir does not step
            (`ermrl.encoders.Encoder.population`) is refused.

    Returns:
        The reason, without a hint (``None``: the population backend applies).
    """
    from ermrl.population._ppo import check_population_config

    if pruner != "none":
        return (
            f"the population backend reports no intermediate returns to --pruner {pruner} "
            "(it trains a whole generation at once)"
        )
    if wandb:
        return "--wandb logs through wandb's callback for the sb3 backend"
    if encoder is not None:
        from ermrl.encoders import get_encoder

        if not get_encoder(encoder).population:
            return f"the population backend does not step --encoder {encoder}'s reservoirs"
    try:
        check_population_config(ppo)
    except (ConfigError, ValueError) as err:
        return str(err).removesuffix(_HINT)
    for task in tasks:
        why = _env_refusal(task)
        if why is not None:
            return why
    return None


def choose_backend(
    requested: str | None,
    ppo: PPOConfig,
    tasks: tuple[TaskConfig, ...] = (),
    *,
    pruner: str = "none",
    wandb: bool = False,
    encoder: str | None = None,
) -> tuple[str, str | None]:
    """The backend of a run: ``requested`` when given, else population where it applies.

    An explicit ``requested`` is returned as it is: the configuration's own checks refuse
    ``--backend population`` where it cannot apply, in one line.

    Args:
        requested: ``--backend`` (``None``: left out, choose).
        ppo: The learner's settings (its ``backend`` is ignored).
        tasks: The envs the runs train on.
        pruner: The study's pruner.
        wandb: The runs log to Weights & Biases.
        encoder: The registered encoder the runs evolve (see
            [`population_refusal`][ermrl.population.population_refusal]).

    Returns:
        ``(backend, why)``: ``why`` is the one-line reason an automatic choice fell back to
        ``sb3`` (``None`` otherwise).
    """
    if requested is not None:
        return requested, None
    why = population_refusal(ppo, tasks, pruner=pruner, wandb=wandb, encoder=encoder)
    return ("sb3", why) if why is not None else ("population", None)
