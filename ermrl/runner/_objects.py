"""The evolution and its selected candidate as objects, the way Optuna and Stable-Baselines3
spell it: an [`Evolution`][ermrl.runner.Evolution] is an Optuna study the user keeps adding
trials to (``optimize(n_trials=...)``); its [`Candidate`][ermrl.runner.Candidate] builds the
selected encoder and trains a learner in front of it (``learn``), which returns a
[`Model`][ermrl.agents.Model] with ``predict``, ``save`` and ``load``.

Both run the code of the ``ermrl evolve`` and ``ermrl test`` commands: the study is created,
resumed and shared as [`evolve`][ermrl.runner.evolve] does it, and the candidate is the trial the
test phase selects ([`select_trial`][ermrl.search.select_trial]).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ermrl.config import ConfigError
from ermrl.storage import DEFAULT_STORAGE

if TYPE_CHECKING:
    import optuna
    import pandas as pd

    from ermrl.agents import Model
    from ermrl.config import EncoderConfig, EvolveConfig, PPOConfig, TaskConfig
    from ermrl.runner._stages import EvolveResult

__all__ = ["Candidate", "Evolution"]


class Evolution:
    """An evolution study that trials are added to, as ``study.optimize(n_trials=...)`` adds
    them to an Optuna study.

    Created from an env id and ``ermrl evolve``'s options (the keywords
    [`evolve`][ermrl.runner.evolve] takes), or from a configuration; an existing study of the same
    name and configuration is resumed. [`load`][ermrl.runner.Evolution.load] opens a study
    by name. Several processes may hold the same study: they share its trials, as several
    ``ermrl evolve`` workers do.

    Args:
        config: An env id, or an ``ermrl.EvolveConfig``.
        storage: The Optuna storage URL.
        study_name: The study's name (default: derived from env, mask and budget).
        **options: With an env id: ``ermrl evolve``'s options (``n_seeds``,
            ``training_steps``, ``observe``, ``ppo``, ...).

    Raises:
        ExperimentError: A bad option (one line, with the nearest valid one).
        ConfigError: A study of that name exists with another configuration.

    Attributes:
        study: The ``optuna.Study``.
        config: The study's configuration.
        storage: Its storage URL.

    Examples:
        >>> import ermrl
        >>> evolution = ermrl.Evolution(
        ...     "CartPole-v1", "sqlite:///objects.db", n_seeds=1, training_steps=1000
        ... )
        >>> evolution.study.study_name
        'CartPole-v1__all__1000steps'
    """

    def __init__(
        self,
        config: EvolveConfig | str,
        storage: str = DEFAULT_STORAGE,
        study_name: str | None = None,
        **options: Any,
    ) -> None:
        from ermrl.runner._stages import _optuna_warnings_only, _resolved_config
        from ermrl.search import create_or_resume_study

        config, command = _resolved_config(config, storage, study_name, None, options)
        name = study_name or config.default_study_name
        with _optuna_warnings_only(True):
            self.study: optuna.Study = create_or_resume_study(
                config, storage, name, command=command
            )
        self.config = config
        self.storage = storage

    @classmethod
    def load(cls, study_name: str, storage: str = DEFAULT_STORAGE) -> Evolution:
        """The evolution of an existing study, with its stored configuration.

        Raises:
            ermrl.storage.StudyNotFound: No such study.
            ConfigError: A study that ``ermrl evolve`` did not create, or one evolved on
                several tasks.
        """
        from ermrl.search import study_config
        from ermrl.storage import load_study

        study = load_study(study_name, storage)
        return cls(study_config(study), storage, study_name)

    def __repr__(self) -> str:
        n = len(self.study.get_trials(deepcopy=False))
        return f"Evolution({self.study.study_name!r}, {self.storage!r}, {n} trials)"

    def optimize(self, n_trials: int | None = None, **keywords: Any) -> EvolveResult:
        """Add trials to the study, then re-evaluate the best candidates when the
        configuration asks (``reevaluate_top``), as ``ermrl evolve`` does.

        Args:
            n_trials: Trials to add: the study ends with the trials it had finished or
                running when the call started, plus ``n_trials`` (a queued reference trial is
                one of them). Calls that overlap in several processes share their trials rather
                than adding them up. ``None``: until the configuration's ``n_trials``.
            **keywords: Keyword arguments of [`evolve`][ermrl.runner.evolve] (``quiet``,
                ``progress``, ``stream``, ``tensorboard``, ``wait_for_running``, ...).

        Returns:
            What [`evolve`][ermrl.runner.evolve] returns: the study's best and selected trials,
            and what this call ran.

        Raises:
            ConfigError: ``n_trials`` is not a positive integer.
            KeyboardInterrupt: Ctrl-C (the running trial is closed and queued again; calling
                ``optimize`` again resumes).
        """
        from optuna.trial import TrialState

        from ermrl.runner._stages import evolve

        config = self.config
        if n_trials is not None:
            if isinstance(n_trials, bool) or not isinstance(n_trials, int) or n_trials < 1:
                raise ConfigError(f"n_trials must be a positive integer, got {n_trials!r}")
            states = (TrialState.COMPLETE, TrialState.PRUNED, TrialState.RUNNING)
            done = len(self.study.get_trials(deepcopy=False, states=states))
            search = dataclasses.replace(config.search, n_trials=done + n_trials)
            config = dataclasses.replace(config, search=search)
        return evolve(config, self.storage, self.study.study_name, **keywords)

    def trials_dataframe(self) -> pd.DataFrame:
        """One row per trial, every state: ``number``, ``state``, ``fitness``, ``duration_s``,
        one column per parameter by its name (``sr``, ``lr``, ``input_scaling``), then the
        CMA-ES ``restart``, ``generation``, ``global_generation``, ``popsize`` and
        ``fail_reason``."""
        from ermrl.analysis import trials_frame

        return trials_frame(self.study).rename(columns={"value": "fitness"})

    def selected(self, trial: int | None = None) -> Candidate:
        """The candidate the test phase selects: the re-evaluated best when a current ranking
        exists, else the best fitness; or trial number ``trial``.

        Raises:
            ConfigError: No completed trial, no such trial, or every re-evaluated candidate
                failed.
        """
        from ermrl.search import decode_candidate, select_trial

        chosen, how = select_trial(self.study, trial)
        encoder, problem = decode_candidate(self.config.space, chosen.params, self.config.problem)
        return Candidate(
            study_name=self.study.study_name,
            storage=self.storage,
            number=chosen.number,
            params=dict(chosen.params),
            fitness=chosen.value,
            selection=how,
            task=problem.task,
            encoder=encoder,
            ppo=problem.ppo,
        )


@dataclass(frozen=True)
class Candidate:
    """A trial of an evolution as the encoder it stands for, ready to train a learner on.

    Attributes:
        study_name: The study.
        storage: Its storage URL.
        number: The trial's number.
        params: Its parameters, as the study holds them (``sr``, ``lr``, ``input_scaling``
            with one reservoir; ``sr_0``, ``sr_1``, ... with several).
        fitness: Its fitness (``None``: not completed).
        selection: How it was selected, in words.
        task: The study's task and observation mask.
        encoder: The encoder's settings with the trial's reservoirs (``None``: a study of a
            learner's genes, which have no encoder).
        ppo: The study's learner settings (with the trial's genes for such a study).
    """

    study_name: str
    storage: str
    number: int
    params: dict[str, float]
    fitness: float | None
    selection: str
    task: TaskConfig
    encoder: EncoderConfig | None
    ppo: PPOConfig

    def make_env(self, n_envs: int = 1, seed: int = 0) -> Any:
        """The task's ``VecEnv`` encoded by this candidate, as a run of seed ``seed`` trains
        on it (the envs and the reservoir weights seeded from ``seed``)."""
        from ermrl.agents import derive_seeds, make_vec_env

        seeds = derive_seeds(seed)
        return make_vec_env(self.task, n_envs, seeds.env, self.encoder, seeds.reservoir)

    def wrap(self, env: Any, seed: int = 0) -> Any:
        """Wrap an env in this candidate's encoder (a ``ReservoirVecEnv``), with the reservoir
        weights of a run of seed ``seed``.

        Args:
            env: A gymnasium env (put in a ``DummyVecEnv``) or a Stable-Baselines3 ``VecEnv``,
                with flat ``Box`` observations.
            seed: The run seed the reservoir weights derive from.

        Returns:
            The ``VecEnv`` whose observations are the encoder's (``env`` as a ``VecEnv``
            without an encoder).
        """
        from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

        from ermrl.agents import derive_seeds
        from ermrl.encoders import encoder_for

        venv = env if isinstance(env, VecEnv) else DummyVecEnv([lambda: env])
        if self.encoder is None:
            return venv
        return encoder_for(self.encoder).wrap_env(venv, self.encoder, derive_seeds(seed).reservoir)

    def learn(self, total_timesteps: int, seed: int = 0) -> Model:
        """Train the study's learner in front of this candidate's encoder on one seed, as a
        test-phase run trains it (the sb3 backend).

        Args:
            total_timesteps: Env steps (an on-policy learner rounds up to whole rollouts).
            seed: Seeds the reservoir weights, the environments and the learner.

        Returns:
            The trained model: ``predict``, ``evaluate``, ``save``, ``get_env``, and
            ``result`` (the training episodes' returns).

        Raises:
            ConfigError: ``total_timesteps`` or ``seed`` out of range.
        """
        from ermrl.agents import train_model

        ppo = dataclasses.replace(self.ppo, backend="sb3")
        return train_model(self.task, self.encoder, ppo, total_timesteps, seed)
