"""Samplers for the outer (evolutionary) loop, including CMA-ES with real restarts.

Optuna >= 4.4 accepts ``CmaEsSampler(restart_strategy=...)`` but silently falls back to
``restart_strategy=None`` (only a ``FutureWarning`` is emitted); restarts moved to an OptunaHub
package, which cannot be downloaded at run time here.
[`RestartCmaEsSampler`][ermrl.search.RestartCmaEsSampler] therefore re-implements the IPOP (Auger &
Hansen 2005) and BIPOP (Hansen 2009) restart strategies on top of `optuna.samplers.CmaEsSampler`, in
the same way Optuna <= 4.3 did.

Every piece of sampler state lives in the study storage as trial system attributes, so any
number of worker processes sharing a storage (or a fresh sampler instance on a reloaded study)
continue the same CMA-ES run, generation and restart. With the default attribute prefix
``"cma:"`` (``"sepcma:"`` for ``use_separable_cma=True``, ``"cmawm:"`` for
``with_margin=True``) the keys are:

* On every trial whose parameters were sampled by CMA-ES:

  - ``cma:n_restarts`` (int): restart index ``k`` of the run that sampled the trial
    (0 for the first run).
  - ``cma:restart_{k}:generation`` (int): generation of run ``k`` the trial belongs to. The key
    contains ``k`` so that trials of an earlier run are never told to the optimizer of a later
    run.
  - ``cma:popsize`` (int): population size of run ``k``.
  - ``cma:regime`` (str): ``"large"`` or ``"small"`` (BIPOP regime of run ``k``; the first run
    and all IPOP runs are ``"large"``).

* On the trial during whose sampling the optimizer was updated (``tell``), additionally:

  - ``cma:state:{i}`` (str): the ``cmaes`` optimizer as plain JSON (`optimizer_state`:
    every attribute, arrays as dtype, shape and base64 bytes, the random generator's state
    included), split into chunks of at most 2045 characters (as Optuna splits its pickle).
    `restore_optimizer` rebuilds it without unpickling or importing anything, and the
    rebuilt optimizer continues exactly as the original.
  - ``cma:restart_state`` (dict): restart bookkeeping matching that optimizer: ``n_restarts``,
    ``regime``, ``popsize`` (current run), ``popsize0`` (first run), ``large_popsize`` (last
    large-regime popsize), ``n_evals_large`` / ``n_evals_small`` (evaluations spent per BIPOP
    regime by finished runs).

The sampler always restores the optimizer and the restart state from the most recent COMPLETE
trial carrying ``cma:state:*``; nothing is kept only in process memory. When that state is
malformed (a chunk cut short or edited, a ``cma:restart_state`` that does not describe a
restart state), a warning is logged and CMA-ES starts a new run, exactly as for a pickled
optimizer below: a resume never crashes on it.

Nothing read from the storage is ever unpickled: anyone who can write to a shared storage could
otherwise run code on every worker. A study written by an older ermrl stored the optimizer
pickled, as ``cma:optimizer:{i}`` (Optuna's format). Those attributes are never read: when the
latest stored state is such a pickle, a warning is logged and CMA-ES starts a new run (restart
index one past the stored ``cma:restart_state``, its popsize and BIPOP budgets, the first run's
start point and step size); the trials already in the study keep their values.

Randomness never depends on which worker asks or how often it asked before:

* each trial's point is drawn from a stream of its own, seeded by ``(seed, trial number)``, so
  workers that share a ``seed`` never draw identical points;
* a restart's randomness (the new start point, and BIPOP's popsize and step size) is seeded by
  state every worker shares: the seed (or, without one, the study name), the restart index and
  the number of the first trial of the generation that ended the run. Workers that restart the same run
  at the same time therefore build the same new optimizer, and every trial labelled
  "restart ``k``" comes from one distribution.

With ``search_space`` given, the space is known before any trial completes, so the first trials
of a study (for example the first 90 of a 90-task SLURM array) come from the CMA-ES initial
distribution, not from an independent random sampler.

Integer (and stepped) genes are searched with margin by default: CMA-ES with Margin (Hamano et
al., GECCO 2022, https://arxiv.org/abs/2205.13482; ``cmaes.CMAwM``) rounds inside the search.
Each sample is encoded to the nearest grid value by the optimizer itself, the unrounded sample is
what is told (``x_for_tell``), and the margin keeps at least a small probability of moving to a
neighbouring integer. Plain CMA-ES with the rounding left to the caller (Optuna's default)
stalls once its step size falls below the grid spacing: every sample rounds to the same integer,
and nothing tells the distribution that its neighbours differ. A trial whose parameters were
fixed (``enqueue_trial``, as the reference trial) is told at its own parameters, not at the point
asked for it.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import warnings
import zlib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any, Literal, cast

import cmaes
import numpy as np
import optuna
from optuna._transform import _SearchSpaceTransform
from optuna.distributions import FloatDistribution, IntDistribution
from optuna.samplers import BaseSampler, CmaEsSampler, RandomSampler, TPESampler
from optuna.study import StudyDirection
from optuna.trial import TrialState

if TYPE_CHECKING:
    from optuna.distributions import BaseDistribution
    from optuna.trial import FrozenTrial

__all__ = [
    "RESTART_STRATEGIES",
    "SAMPLERS",
    "RestartCmaEsSampler",
    "RestartStrategy",
    "SamplerName",
    "cma_generation_info",
    "check_optimizer",
    "has_discrete_genes",
    "make_sampler",
    "optimizer_state",
    "restore_optimizer",
]

RestartStrategy = Literal["none", "ipop", "bipop"]
SamplerName = Literal["cmaes", "tpe", "random"]
SAMPLERS: tuple[str, ...] = ("cmaes", "tpe", "random")
RESTART_STRATEGIES: tuple[str, ...] = ("none", "ipop", "bipop")

CmaClass = cmaes.CMA | cmaes.SepCMA | cmaes.CMAwM

_logger = logging.getLogger(__name__)

# Same constants as optuna.samplers._cmaes.
_EPS = 1e-10
_ATTR_PREFIXES: tuple[str, ...] = ("cma:", "sepcma:", "cmawm:")
_MIN_POPSIZE = 2


@dataclass(frozen=True)
class _RestartState:
    """Restart bookkeeping stored next to the optimizer's state.

    Attributes:
        n_restarts: Index of the current run (number of restarts done so far).
        regime: ``"large"`` or ``"small"``; the BIPOP regime of the current run.
        popsize: Population size of the current run.
        popsize0: Population size of the first run (default popsize for BIPOP).
        large_popsize: Population size of the last large-regime run.
        n_evals_large: Evaluations spent by finished large-regime runs.
        n_evals_small: Evaluations spent by finished small-regime runs.
    """

    n_restarts: int
    regime: str
    popsize: int
    popsize0: int
    large_popsize: int
    n_evals_large: int = 0
    n_evals_small: int = 0

    @classmethod
    def initial(cls, popsize: int) -> _RestartState:
        """State of the first run.

        Args:
            popsize: Population size of the first run.

        Returns:
            The state with no restart done and no budget spent.
        """
        return cls(
            n_restarts=0, regime="large", popsize=popsize, popsize0=popsize, large_popsize=popsize
        )

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> _RestartState:
        """Rebuild a state from its stored (JSON) form.

        Args:
            raw: The dictionary stored under ``{prefix}restart_state``.

        Returns:
            The restart state.

        Raises:
            ValueError: A field is not an integer, a count is negative, a population size is
                below 2 or the regime is neither ``"large"`` nor ``"small"``.
        """
        state = cls(
            n_restarts=int(raw["n_restarts"]),
            regime=str(raw["regime"]),
            popsize=int(raw["popsize"]),
            popsize0=int(raw["popsize0"]),
            large_popsize=int(raw["large_popsize"]),
            n_evals_large=int(raw.get("n_evals_large", 0)),
            n_evals_small=int(raw.get("n_evals_small", 0)),
        )
        if state.regime not in ("large", "small"):
            raise ValueError(f"unknown regime {state.regime!r}")
        if min(state.n_restarts, state.n_evals_large, state.n_evals_small) < 0:
            raise ValueError("a negative restart or evaluation count")
        if min(state.popsize, state.popsize0, state.large_popsize) < _MIN_POPSIZE:
            raise ValueError(f"a population size below {_MIN_POPSIZE}")
        return state


class RestartCmaEsSampler(CmaEsSampler):
    """CMA-ES with IPOP / BIPOP restarts implemented locally (Auger & Hansen 2005; Hansen 2009).

    Behaves like `optuna.samplers.CmaEsSampler` (the ``cmaes`` backend) and additionally
    restarts the optimizer whenever ``optimizer.should_stop()`` is true after an update:

    * ``"ipop"``: every restart starts at a uniformly random point of the search space with the
      default step size and ``popsize = previous_large_popsize * inc_popsize``.
    * ``"bipop"``: alternates between a *large* regime (popsize multiplied by ``inc_popsize`` at
      each large restart) and a *small* regime with
      ``popsize = floor(popsize0 * (0.5 * large_popsize / popsize0) ** (U1 ** 2))`` and
      ``sigma = sigma0 * 10 ** (-2 * U2)`` (``U1, U2 ~ U[0, 1]``). The regime with fewer
      evaluations spent so far is chosen; the first run counts as large.
    * ``"none"``: never restarts (plain Optuna behaviour).

    All state (optimizer, restart index, popsize, BIPOP budgets and regime) is kept in trial
    system attributes; see the module docstring for the keys.

    Args:
        restart_strategy: ``"none"``, ``"ipop"`` or ``"bipop"``.
        inc_popsize: Multiplier of the large-regime population size at each (large) restart.
            Must be >= 2.
        popsize: Population size of the first run; ``None`` uses the ``cmaes`` default
            ``4 + floor(3 ln n)``. Must be >= 2.
        seed: Seed for the CMA-ES random generator and the default independent sampler.
        n_startup_trials: Number of COMPLETE trials sampled by the independent sampler before
            CMA-ES takes over. Without ``search_space``, the first trial of a study is always
            sampled independently, because the search space is unknown until one trial has
            finished.
        search_space: The fixed search space (parameter name -> distribution). When given,
            CMA-ES samples from the first trial on: trials asked before any trial completes
            come from the initial distribution.
        x0: Start point of the first run (parameter name -> value, external representation);
            ``None``: the centre of the (transformed) box, as in Optuna.
        with_margin: Search with CMA-ES with Margin (``cmaes.CMAwM``): integer and stepped
            genes are rounded inside the search. ``None`` (default): on when ``search_space``
            has such a gene on a linear scale (and neither ``use_separable_cma`` nor
            ``lr_adapt``, which Optuna cannot combine with it, is asked), off otherwise.
        **kwargs: Further keyword arguments of `optuna.samplers.CmaEsSampler`
            (e.g. ``independent_sampler``, ``consider_pruned_trials``, ``use_separable_cma``,
            ``lr_adapt``). ``restart_strategy``/``inc_popsize`` are never
            forwarded, so constructing this sampler emits no deprecation warning.

    Raises:
        ValueError: For an unknown ``restart_strategy``, ``inc_popsize < 2`` or ``popsize < 2``.
    """

    def __init__(
        self,
        *,
        restart_strategy: RestartStrategy = "none",
        inc_popsize: int = 2,
        popsize: int | None = None,
        seed: int | None = None,
        n_startup_trials: int = 0,
        search_space: Mapping[str, BaseDistribution] | None = None,
        x0: Mapping[str, float] | None = None,
        with_margin: bool | None = None,
        **kwargs: Any,
    ) -> None:
        if restart_strategy not in RESTART_STRATEGIES:
            raise ValueError(
                f"Unknown restart strategy {restart_strategy!r}; "
                f"expected one of {RESTART_STRATEGIES}."
            )
        if isinstance(inc_popsize, bool) or not isinstance(inc_popsize, int) or inc_popsize < 2:
            raise ValueError(f"inc_popsize must be an integer >= 2, got {inc_popsize!r}.")
        _check_popsize(popsize)
        if n_startup_trials < 0:
            raise ValueError(f"n_startup_trials must be >= 0, got {n_startup_trials!r}.")
        if x0 is not None and search_space is not None and set(x0) != set(search_space):
            raise ValueError(
                f"x0 must name exactly the parameters of the search space {sorted(search_space)}, "
                f"got {sorted(x0)}."
            )
        auto = with_margin is None
        if with_margin is None:
            with_margin = (
                search_space is not None
                and has_discrete_genes(search_space)
                and not kwargs.get("use_separable_cma", False)
                and not kwargs.get("lr_adapt", False)
            )
        with warnings.catch_warnings():
            if auto:  # chosen here, not asked for: Optuna's "experimental" warning is noise
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            super().__init__(
                seed=seed,
                n_startup_trials=n_startup_trials,
                popsize=popsize,
                with_margin=with_margin,
                **kwargs,
            )
        # Optuna deprecates `x0`; the start point is handled here (`_init_optimizer`).
        self._x0 = None if x0 is None else dict(x0)
        self._fixed_space = None if search_space is None else dict(search_space)
        self._seed = seed
        # Without a seed, points still differ per trial; this process's entropy keeps studies apart.
        self._entropy = (
            int(seed) if seed is not None else int(np.random.SeedSequence().generate_state(1)[0])
        )
        self._restart_strategy: RestartStrategy = restart_strategy
        self._inc_popsize = inc_popsize
        self._warned_legacy = False
        self._warned_malformed = False

    @property
    def restart_strategy(self) -> RestartStrategy:
        """The restart strategy (``"none"``, ``"ipop"`` or ``"bipop"``)."""
        return self._restart_strategy

    @property
    def inc_popsize(self) -> int:
        """Multiplier of the large-regime population size at each restart."""
        return self._inc_popsize

    # ------------------------------------------------------------------ attribute keys

    @property
    def _attr_key_n_restarts(self) -> str:
        return self._attr_prefix + "n_restarts"

    @property
    def _attr_key_popsize(self) -> str:
        return self._attr_prefix + "popsize"

    @property
    def _attr_key_regime(self) -> str:
        return self._attr_prefix + "regime"

    @property
    def _attr_key_restart_state(self) -> str:
        return self._attr_prefix + "restart_state"

    @property
    def _attr_key_state(self) -> str:
        return self._attr_prefix + "state"

    def _attr_key_restart_generation(self, n_restarts: int) -> str:
        return f"{self._attr_prefix}restart_{n_restarts}:generation"

    # ------------------------------------------------------------------ randomness

    def _trial_rng_seed(self, trial: FrozenTrial) -> int:
        """Seed of the point drawn for ``trial``: its own stream, whichever worker asks."""
        return _derive_seed(self._entropy, trial.number)

    def _restart_rng(
        self, study: optuna.Study, n_restarts: int, first_trial: int
    ) -> np.random.RandomState:
        """Generator of restart ``n_restarts``, seeded from state shared by every worker.

        Args:
            study: The study (its name seeds the restart when the sampler has no seed).
            n_restarts: Index of the new run.
            first_trial: Number of the first trial of the generation that ended the previous run.
        """
        # With a seed the run is reproducible in any study; without one, the study's name is
        # the state all workers share.
        base = zlib.crc32(study.study_name.encode()) if self._seed is None else self._seed
        seed = _derive_seed(base, int(self._seed is None), n_restarts, first_trial)
        return np.random.RandomState(seed)

    # ------------------------------------------------------------------ sampling

    def infer_relative_search_space(
        self, study: optuna.Study, trial: FrozenTrial
    ) -> dict[str, BaseDistribution]:
        """The fixed search space when one was given, else Optuna's intersection search space."""
        if self._fixed_space is not None:
            return {k: d for k, d in self._fixed_space.items() if not d.single()}
        return super().infer_relative_search_space(study, trial)

    def sample_relative(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        search_space: dict[str, BaseDistribution],
    ) -> dict[str, Any]:
        """Sample all parameters of the relative search space from the current CMA-ES run.

        Restores the optimizer and restart state from the storage, tells it the finished
        generation if complete (restarting it when it should stop), asks a new point and
        records the run/generation/popsize of this trial in its system attributes.

        Args:
            study: The study.
            trial: The trial being sampled.
            search_space: The relative search space.

        Returns:
            The sampled parameters (external representation), or ``{}`` while in the startup
            phase or when the search space is empty.
        """
        self._raise_error_if_multi_objective(study)

        if len(search_space) == 0:
            return {}

        completed_trials = self._get_trials(study)
        if len(completed_trials) < self._n_startup_trials:
            return {}

        # With `with_margin=True`, bounds of discrete dimensions are handled inside `CMAwM`.
        trans = _SearchSpaceTransform(
            search_space, transform_step=not self._with_margin, transform_0_1=True
        )

        optimizer, state = self._current_run(completed_trials, trans, study.direction)
        if optimizer.dim != len(trans.bounds):
            # Not silent: the search space changed, CMA-ES cannot continue.
            _logger.warning(
                "RestartCmaEsSampler: the search space changed (dimension %d -> %d); "
                "%s is used instead of CMA-ES for trial %d.",
                optimizer.dim,
                len(trans.bounds),
                self._independent_sampler.__class__.__name__,
                trial.number,
            )
            return {}
        optimizer, state = self._tell_generation(
            study, trial, completed_trials, optimizer, state, trans
        )
        return trans.untransform(self._ask(study, trial, optimizer, state))

    def _current_run(
        self,
        completed_trials: list[FrozenTrial],
        trans: _SearchSpaceTransform,
        direction: StudyDirection,
    ) -> tuple[CmaClass, _RestartState]:
        """The optimizer and restart state of the current run: restored from the storage, or new.

        Args:
            completed_trials: The study's completed trials (`_get_trials`).
            trans: Search-space transform.
            direction: Study direction.

        Returns:
            The optimizer and its restart state (a new first run when none is stored; a new
            optimizer at the stored population size when a pickled one was left unread).
        """
        optimizer, state = self._restore_state(completed_trials)
        if optimizer is None and state is not None:  # a pickled optimizer was left unread
            optimizer = self._init_optimizer(
                trans, direction, population_size=state.popsize or self._popsize
            )
            popsize = optimizer.population_size
            state = replace(
                state,
                popsize=popsize,
                popsize0=state.popsize0 or popsize,
                large_popsize=state.large_popsize or popsize,
            )
        elif optimizer is None or state is None:
            optimizer = self._init_optimizer(trans, direction, population_size=self._popsize)
            state = _RestartState.initial(optimizer.population_size)
        return optimizer, state

    def _tell_generation(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        completed_trials: list[FrozenTrial],
        optimizer: CmaClass,
        state: _RestartState,
        trans: _SearchSpaceTransform,
    ) -> tuple[CmaClass, _RestartState]:
        """Tell the optimizer its generation once complete, restart it if it should stop, and
        store the new state on ``trial``.

        Args:
            study: The study.
            trial: The trial being sampled (the state is stored on it).
            completed_trials: The study's completed trials.
            optimizer: The current run's optimizer.
            state: Its restart state.
            trans: Search-space transform.

        Returns:
            The optimizer and restart state to ask (unchanged while the generation is not
            complete).
        """
        solution_trials = self._solution_trials(
            completed_trials, state.n_restarts, optimizer.generation
        )
        if len(solution_trials) < optimizer.population_size:
            return optimizer, state
        solutions: list[tuple[np.ndarray, float]] = []
        for t in solution_trials[: optimizer.population_size]:
            assert t.value is not None, "completed trials must have a value"
            if isinstance(optimizer, cmaes.CMAwM) and "fixed_params" not in t.system_attrs:
                x = np.array(t.system_attrs["x_for_tell"])
            else:  # plain CMA-ES, or a trial whose parameters were fixed (enqueued)
                x = trans.transform(t.params)
            y = t.value if study.direction == StudyDirection.MINIMIZE else -t.value
            solutions.append((x, y))
        optimizer.tell(solutions)

        if self._restart_strategy != "none" and optimizer.should_stop():
            rng = self._restart_rng(study, state.n_restarts + 1, solution_trials[0].number)
            optimizer, state = self._restart(optimizer, state, trans, study.direction, rng)

        self._store_state(study, trial, optimizer, state)
        return optimizer, state

    def _ask(
        self, study: optuna.Study, trial: FrozenTrial, optimizer: CmaClass, state: _RestartState
    ) -> np.ndarray:
        """Ask a point for ``trial`` (internal representation) and record its run, generation,
        population size and regime in the trial's system attributes."""
        # Reseed the optimizer for every trial, from the trial's own stream.
        optimizer._rng.seed(self._trial_rng_seed(trial))
        if isinstance(optimizer, cmaes.CMAwM):
            params, x_for_tell = optimizer.ask()
            study._storage.set_trial_system_attr(trial._trial_id, "x_for_tell", x_for_tell.tolist())
        else:
            params = optimizer.ask()

        storage = study._storage
        storage.set_trial_system_attr(trial._trial_id, self._attr_key_n_restarts, state.n_restarts)
        storage.set_trial_system_attr(
            trial._trial_id,
            self._attr_key_restart_generation(state.n_restarts),
            optimizer.generation,
        )
        storage.set_trial_system_attr(
            trial._trial_id, self._attr_key_popsize, optimizer.population_size
        )
        storage.set_trial_system_attr(trial._trial_id, self._attr_key_regime, state.regime)
        return params

    def sample_independent(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        param_name: str,
        param_distribution: BaseDistribution,
    ) -> Any:
        """Sample a parameter outside the relative search space with the independent sampler.

        Unlike the parent, no warning is logged while no trial has completed yet (the search
        space is necessarily unknown then); afterwards every fallback is logged (if
        ``warn_independent_sampling``).

        Args:
            study: The study.
            trial: The trial being sampled.
            param_name: Name of the parameter.
            param_distribution: Its distribution.

        Returns:
            The sampled value.
        """
        self._raise_error_if_multi_objective(study)
        if self._warn_independent_sampling:
            n_complete = len(self._get_trials(study))
            if n_complete > 0 and n_complete >= self._n_startup_trials:
                self._log_independent_sampling(trial, param_name)
        return self._independent_sampler.sample_independent(
            study, trial, param_name, param_distribution
        )

    # ------------------------------------------------------------------ helpers

    def _solution_trials(
        self, trials: list[FrozenTrial], n_restarts: int, generation: int
    ) -> list[FrozenTrial]:
        """Completed trials sampled in generation ``generation`` of run ``n_restarts``."""
        key = self._attr_key_restart_generation(n_restarts)
        return [t for t in trials if t.system_attrs.get(key, -1) == generation]

    def _restore_state(
        self, completed_trials: list[FrozenTrial]
    ) -> tuple[CmaClass | None, _RestartState | None]:
        """Load the optimizer and restart state of the latest trial that stored them.

        The state is plain data (`restore_optimizer`); nothing is unpickled. When the
        latest stored state is an optimizer pickled by an older ermrl (``{prefix}optimizer:*``),
        it is left unread: a warning is logged and a new run starts (see
        `_legacy_restart`). A malformed state (chunks that do not decode to an
        optimizer, a restart state that is not one) is handled the same way, with its own
        warning (`_malformed_restart`).

        Args:
            completed_trials: Completed trials, ordered by trial number.

        Returns:
            ``(optimizer, state)``, or ``(None, None)`` when none was stored yet.
        """
        state_prefix = self._attr_key_state + ":"
        pickle_prefix = self._attr_key_optimizer + ":"
        for t in reversed(completed_trials):
            chunks = {k: v for k, v in t.system_attrs.items() if k.startswith(state_prefix)}
            raw = t.system_attrs.get(self._attr_key_restart_state)
            if chunks:
                try:
                    optimizer = restore_optimizer(json.loads(_join_chunks(chunks, state_prefix)))
                    # Read what sample_relative needs now, so a hollow optimizer fails here.
                    population_size = int(optimizer.population_size)
                    if min(population_size, int(optimizer.dim), int(optimizer.generation)) < 0:
                        raise ValueError("negative popsize, dimension or generation")
                    if raw is None:
                        state = _RestartState.initial(population_size)
                    elif isinstance(raw, dict):
                        state = _RestartState.from_dict(raw)
                    else:
                        raise TypeError(f"{self._attr_key_restart_state} is not a mapping")
                except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as err:
                    return None, self._malformed_restart(t, raw, err)
                return optimizer, state
            if any(k.startswith(pickle_prefix) for k in t.system_attrs):
                return None, self._legacy_restart(t, raw)
        return None, None

    def _legacy_restart(self, trial: FrozenTrial, raw: Any) -> _RestartState:
        """Restart state of the run that replaces an optimizer pickled by an older ermrl.

        Args:
            trial: The trial carrying the pickled optimizer (never unpickled).
            raw: Its ``{prefix}restart_state`` (plain JSON), if any.

        Returns:
            The state of a new run: restart index one past the stored one (so its trials are
            never told to the old run), the stored popsize and BIPOP budgets. The caller builds
            its optimizer as the first run's (start point, step size), the same in every worker.
        """
        old = self._stored_restart_state(trial, raw)
        if not self._warned_legacy:
            _logger.warning(
                "RestartCmaEsSampler: trial %d holds a CMA-ES optimizer pickled by an older "
                "ermrl (%s*); it is ignored, never unpickled, and CMA-ES starts run %d afresh.",
                trial.number,
                self._attr_key_optimizer + ":",
                old.n_restarts + 1,
            )
            self._warned_legacy = True
        return replace(old, n_restarts=old.n_restarts + 1)

    def _malformed_restart(self, trial: FrozenTrial, raw: Any, error: Exception) -> _RestartState:
        """Restart state of the run that replaces a malformed stored CMA-ES state.

        As `_legacy_restart`: the state is ignored (one warning per sampler), and a new
        run starts with a restart index one past the stored one, so that the trials of the run
        whose state was lost are never told to the new optimizer. The trials keep their values.

        Args:
            trial: The trial carrying the malformed state.
            raw: Its ``{prefix}restart_state``, if any (used when it is readable).
            error: Why the state could not be read.

        Returns:
            The state of the new run.
        """
        old = self._stored_restart_state(trial, raw)
        if not self._warned_malformed:
            reason = str(error).strip().splitlines()[0] if str(error).strip() else ""
            _logger.warning(
                "RestartCmaEsSampler: trial %d holds a malformed CMA-ES state (%s: %s); it is "
                "ignored, and CMA-ES starts run %d afresh (the trials in the study are kept).",
                trial.number,
                type(error).__name__,
                reason,
                old.n_restarts + 1,
            )
            self._warned_malformed = True
        return replace(old, n_restarts=old.n_restarts + 1)

    def _stored_restart_state(self, trial: FrozenTrial, raw: Any) -> _RestartState:
        """The restart state stored on ``trial``, or what its labels tell when it is unreadable.

        Args:
            trial: A trial that stored (or tried to store) the sampler's state.
            raw: Its ``{prefix}restart_state``, if any.

        Returns:
            The stored state; failing that, the first run's with the trial's restart index
            (``{prefix}n_restarts``, 0 when missing) and popsize 0 (the caller's default).
        """
        if isinstance(raw, dict):
            try:
                return _RestartState.from_dict(raw)
            except (KeyError, TypeError, ValueError):
                pass
        label = trial.system_attrs.get(self._attr_key_n_restarts, 0)
        n_restarts = label if isinstance(label, int) and label >= 0 else 0
        return replace(_RestartState.initial(self._popsize or 0), n_restarts=n_restarts)

    def _store_state(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        optimizer: CmaClass,
        state: _RestartState,
    ) -> None:
        """Persist the optimizer (plain JSON, chunked) and the restart state on ``trial``."""
        text = json.dumps(optimizer_state(optimizer), allow_nan=False, separators=(",", ":"))
        prefix = self._attr_key_state + ":"
        attrs: dict[str, Any] = {
            f"{prefix}{i}": text[start : start + _CHUNK_CHARS]
            for i, start in enumerate(range(0, len(text), _CHUNK_CHARS))
        }
        attrs[self._attr_key_restart_state] = asdict(state)
        for key, value in attrs.items():
            study._storage.set_trial_system_attr(trial._trial_id, key, value)

    def _restart(
        self,
        optimizer: CmaClass,
        state: _RestartState,
        trans: _SearchSpaceTransform,
        direction: StudyDirection,
        rng: np.random.RandomState,
    ) -> tuple[CmaClass, _RestartState]:
        """Start a new run after ``optimizer`` stopped.

        Args:
            optimizer: The optimizer that should stop (already told its last generation).
            state: Restart state of the finished run.
            trans: Search-space transform.
            direction: Study direction.
            rng: The restart's generator (see `_restart_rng`): every worker that restarts
                this run draws the same popsize, step size and start point.

        Returns:
            The new optimizer (generation 0) and the matching restart state.
        """
        n_evals = optimizer.population_size * optimizer.generation
        if state.regime == "small":
            state = replace(state, n_evals_small=state.n_evals_small + n_evals)
        else:
            state = replace(state, n_evals_large=state.n_evals_large + n_evals)

        sigma_factor = 1.0
        if self._restart_strategy == "bipop" and state.n_evals_small < state.n_evals_large:
            u_popsize, u_sigma = float(rng.uniform()), float(rng.uniform())
            popsize = math.floor(
                state.popsize0 * (0.5 * state.large_popsize / state.popsize0) ** (u_popsize**2)
            )
            popsize = max(_MIN_POPSIZE, popsize)
            sigma_factor = 10.0 ** (-2.0 * u_sigma)
            state = replace(state, n_restarts=state.n_restarts + 1, regime="small", popsize=popsize)
        else:
            popsize = state.large_popsize * self._inc_popsize
            state = replace(
                state,
                n_restarts=state.n_restarts + 1,
                regime="large",
                popsize=popsize,
                large_popsize=popsize,
            )

        _logger.info(
            "CMA-ES (%s) restart %d after %d generations of popsize %d: new popsize %d (%s)",
            self._restart_strategy,
            state.n_restarts,
            optimizer.generation,
            optimizer.population_size,
            popsize,
            state.regime,
        )
        new_optimizer = self._init_optimizer(
            trans,
            direction,
            population_size=popsize,
            randomize_start_point=True,
            sigma_factor=sigma_factor,
            rng=rng,
        )
        return new_optimizer, state

    def _init_optimizer(
        self,
        trans: _SearchSpaceTransform,
        direction: StudyDirection,
        *,
        population_size: int | None = None,
        randomize_start_point: bool = False,
        sigma_factor: float = 1.0,
        rng: np.random.RandomState | None = None,
    ) -> CmaClass:
        """Create a ``cmaes`` optimizer (same choices as Optuna's ``CmaEsSampler``).

        Args:
            trans: Search-space transform (bounds are ``[0, 1]`` per dimension).
            direction: Study direction (used for warm starting).
            population_size: Population size; ``None`` for the ``cmaes`` default.
            randomize_start_point: Draw the mean uniformly within the bounds (restarts). Warm
                starting from ``source_trials`` and ``x0`` only apply to the first run.
            sigma_factor: Multiplier of the initial step size (BIPOP small regime).
            rng: Generator of the start point and the optimizer's seed (``None``: a fixed
                seed derived from the sampler's seed; the first run is the same in every worker).

        Returns:
            The new optimizer.
        """
        if rng is None:
            rng = np.random.RandomState(_derive_seed(-1 if self._seed is None else self._seed))
        mean, sigma0, cov = self._start_point(trans, direction, randomize_start_point, rng)
        sigma = max(sigma0 * sigma_factor, _EPS)
        seed = int(rng.randint(1, 2**31 - 2))
        return self._new_cma(trans, mean, sigma, cov, seed, population_size)

    def _start_point(
        self,
        trans: _SearchSpaceTransform,
        direction: StudyDirection,
        randomize_start_point: bool,
        rng: np.random.RandomState,
    ) -> tuple[np.ndarray, float, np.ndarray | None]:
        """The mean, step size and covariance a new run starts from.

        In this order: a uniform draw within the bounds (restarts), a warm start from
        ``source_trials``, ``x0`` (clipped to the bounds), or the centre of the box.

        Args:
            trans: Search-space transform (bounds are ``[0, 1]`` per dimension).
            direction: Study direction (the sign of the warm start's values).
            randomize_start_point: Draw the mean uniformly within the bounds.
            rng: Generator of the drawn mean.

        Returns:
            ``(mean, sigma0, cov)``: the mean, shape ``(n_dimension,)``, the initial step size
            (a sixth of the narrowest range unless ``sigma0`` was given) and the covariance
            (``None`` unless warm started).
        """
        lower_bounds = trans.bounds[:, 0]
        upper_bounds = trans.bounds[:, 1]
        n_dimension = len(trans.bounds)
        cov: np.ndarray | None = None

        if self._sigma0 is None:
            sigma0 = float(np.min((upper_bounds - lower_bounds) / 6))
        else:
            sigma0 = float(self._sigma0)

        if randomize_start_point:
            mean = lower_bounds + (upper_bounds - lower_bounds) * rng.rand(n_dimension)
        elif self._source_trials is not None:
            expected_states = [TrialState.COMPLETE]
            if self._consider_pruned_trials:
                expected_states.append(TrialState.PRUNED)
            sign = 1 if direction == StudyDirection.MINIMIZE else -1
            source_solutions = [
                (trans.transform(t.params), sign * cast("float", t.value))
                for t in self._source_trials
                if t.state in expected_states and _is_compatible(trans, t.distributions)
            ]
            if len(source_solutions) == 0:
                raise ValueError("No compatible source_trials")
            mean, sigma0, cov = cmaes.get_warm_start_mgd(source_solutions)
        elif self._x0 is not None:
            mean = np.clip(trans.transform(self._x0), lower_bounds, upper_bounds)
        else:
            mean = lower_bounds + (upper_bounds - lower_bounds) / 2
        return mean, sigma0, cov

    def _new_cma(
        self,
        trans: _SearchSpaceTransform,
        mean: np.ndarray,
        sigma: float,
        cov: np.ndarray | None,
        seed: int,
        population_size: int | None,
    ) -> CmaClass:
        """The ``cmaes`` optimizer the sampler's settings ask for: ``SepCMA``, ``CMAwM`` or
        ``CMA``.

        Args:
            trans: Search-space transform (bounds and, for ``CMAwM``, the genes' steps).
            mean: Start point, shape ``(n_dimension,)``.
            sigma: Initial step size.
            cov: Initial covariance, shape ``(n_dimension, n_dimension)`` (``None``: identity;
                ``SepCMA`` takes none).
            seed: The optimizer's seed.
            population_size: Population size; ``None`` for the ``cmaes`` default.

        Returns:
            The new optimizer.
        """
        n_dimension = len(trans.bounds)
        # cmaes divides by the rank-mu learning rate, which is 0 for popsize < 4 (mu = 1); the
        # resulting inf is discarded by a min(), so the warning is noise.
        if self._use_separable_cma and n_dimension == 1:
            warnings.warn(
                "Separable CMA-ES does not operate meaningfully on single-dimensional search "
                "spaces. The setting `use_separable_cma=True` will be ignored.",
                UserWarning,
                stacklevel=3,  # _init_optimizer's caller
            )
        with np.errstate(divide="ignore"):
            if self._use_separable_cma and n_dimension > 1:
                return cmaes.SepCMA(
                    mean=mean,
                    sigma=sigma,
                    bounds=trans.bounds,
                    seed=seed,
                    n_max_resampling=10 * n_dimension,
                    population_size=population_size,
                )
            if self._with_margin:
                return cmaes.CMAwM(
                    mean=mean,
                    sigma=sigma,
                    bounds=trans.bounds,
                    steps=_margin_steps(trans),
                    cov=cov,
                    seed=seed,
                    n_max_resampling=10 * n_dimension,
                    population_size=population_size,
                )
            return cmaes.CMA(
                mean=mean,
                sigma=sigma,
                cov=cov,
                bounds=trans.bounds,
                seed=seed,
                n_max_resampling=10 * n_dimension,
                population_size=population_size,
                lr_adapt=self._lr_adapt,
            )


def _margin_steps(trans: _SearchSpaceTransform) -> np.ndarray:
    """The step of each gene for ``cmaes.CMAwM``, as a share of its range, shape
    ``(n_dimension,)``: 0 for a continuous or log-scale gene, 1 for a gene fixed to one value."""
    steps = np.empty(len(trans.bounds), dtype=float)
    for i, dist in enumerate(trans._search_space.values()):
        assert isinstance(dist, (IntDistribution, FloatDistribution))
        if dist.step is None or dist.log:
            steps[i] = 0.0
        elif dist.low == dist.high:
            steps[i] = 1.0
        else:
            steps[i] = dist.step / (dist.high - dist.low)
    return steps


# ---------------------------------------------------------------------- plain-data optimizer state

# The only classes a stored state may name: restoring never imports or calls anything else.
_OPTIMIZER_CLASSES: dict[str, type[CmaClass]] = {
    "CMA": cmaes.CMA,
    "SepCMA": cmaes.SepCMA,
    "CMAwM": cmaes.CMAwM,
}
# Array dtypes a stored state may use (no object, string or structured dtypes).
_ARRAY_KINDS = "biuf"
# Optuna's RDB storage limits one attribute value; the JSON text is split into chunks.
_CHUNK_CHARS = 2045


def optimizer_state(optimizer: CmaClass) -> dict[str, Any]:
    """The complete state of a ``cmaes`` optimizer as plain, JSON-serializable data.

    Every attribute of the optimizer is kept (mean, step size, covariance, evolution paths,
    generation, popsize, bounds, learning rates, termination history and the random
    generator's state), so `restore_optimizer` gives an optimizer that continues exactly
    as this one would. Arrays are stored bit-exactly (``dtype``, ``shape`` and base64 bytes);
    non-finite floats as ``{"__float__": "inf"}``.

    Args:
        optimizer: A ``cmaes.CMA``, ``cmaes.SepCMA`` or ``cmaes.CMAwM``.

    Returns:
        A dict of JSON types only (``json.dumps`` accepts it with ``allow_nan=False``).

    Raises:
        TypeError: For another optimizer class or an attribute of a type that has no plain form.
    """
    encoded = _encode(optimizer)
    assert isinstance(encoded, dict)
    return encoded


def restore_optimizer(state: Mapping[str, Any]) -> CmaClass:
    """Rebuild an optimizer from `optimizer_state`, without running any stored code.

    The state can only name ``CMA``, ``SepCMA`` or ``CMAwM`` and hold numbers, strings, lists
    and numeric arrays; nothing is unpickled or imported.

    Args:
        state: The plain state.

    Returns:
        The optimizer.

    Raises:
        ValueError: For a state that is not of that form, or an optimizer that is not whole and
            usable (`check_optimizer`).
    """
    try:
        optimizer = _decode(dict(state))
    except RecursionError:  # nested deeper than any state ermrl writes
        raise ValueError("the stored CMA-ES state is nested too deep") from None
    if not isinstance(optimizer, tuple(_OPTIMIZER_CLASSES.values())):
        raise ValueError("the stored CMA-ES state does not describe a cmaes optimizer")
    check_optimizer(cast("CmaClass", optimizer))
    return cast("CmaClass", optimizer)


def check_optimizer(optimizer: CmaClass) -> None:
    """Check that a restored optimizer is whole and can go on: shapes, finiteness, positivity.

    A state edited by hand or written by a bad disk can decode to an optimizer whose ``ask`` or
    ``tell`` fails (an ``IndexError`` on a wrong-length mean, a ``ValueError`` on a NaN, a
    division by a zero popsize) on every resume. With ``n`` the dimension and ``λ`` the
    population size: ``_n_dim`` ``n >= 1``, ``_popsize`` ``λ >= 2``, ``1 <= _mu <= λ``; the
    mean and both evolution paths have shape ``(n,)``, the covariance ``(n, n)`` (``(n,)`` for
    ``SepCMA``), the weights ``(λ,)`` (``(μ,)`` for ``SepCMA``), the bounds ``(n, 2)``; all of
    them finite; the step size and the learning rates are finite numbers, the step size and
    ``μ_eff``, ``c_σ``, ``d_σ``, ``χ_n`` positive. ``CMAwM`` is checked with its inner
    ``CMA``. Last, a copy of the optimizer must ``ask`` a finite point of shape ``(n,)``.

    Args:
        optimizer: The restored optimizer (left unchanged).

    Raises:
        ValueError: The first thing found wrong.
    """
    import copy

    cma: Any = optimizer
    if isinstance(optimizer, cmaes.CMAwM):
        cma = getattr(optimizer, "_cma", None)
        if type(cma) is not cmaes.CMA:
            raise ValueError("a CMAwM state without its inner CMA")
    n = _int_attr(cma, "_n_dim", 1)
    popsize = _int_attr(cma, "_popsize", _MIN_POPSIZE)
    mu = _int_attr(cma, "_mu", 1, popsize)
    _int_attr(cma, "_g", 0)
    _int_attr(cma, "_n_max_resampling", 0)
    separable = isinstance(cma, cmaes.SepCMA)
    for name in ("_mean", "_p_sigma", "_pc"):
        _array_attr(cma, name, (n,))
    _array_attr(cma, "_C", (n,) if separable else (n, n))
    _array_attr(cma, "_weights", (mu,) if separable else (popsize,))
    _array_attr(cma, "_D", (n,), optional=True)
    if not separable:
        _array_attr(cma, "_B", (n, n), optional=True)
    _array_attr(cma, "_bounds", (n, 2), optional=True)
    for name in ("_sigma", "_mu_eff", "_c_sigma", "_d_sigma", "_chi_n"):
        _real_attr(cma, name, positive=True)
    for name in ("_cc", "_c1", "_cmu", "_cm"):
        _real_attr(cma, name)
    if not isinstance(getattr(cma, "_rng", None), np.random.RandomState):
        raise ValueError("the stored CMA-ES state has no random generator")
    if isinstance(optimizer, cmaes.CMAwM):
        _array_attr(optimizer, "_A", (n,))
        _real_attr(optimizer, "margin", positive=True)
        n_discrete = _int_attr(optimizer, "_n_zdim", 0, n)
        for name in ("_discrete_space_low", "_discrete_space_size", "_discrete_space_step"):
            _array_attr(optimizer, name, (n_discrete,))
        for name in ("m_z_lim_low", "m_z_lim_up"):
            _array_attr(optimizer, name, (n_discrete,))
        discrete = _array_attr(optimizer, "_discrete_idx", (n_discrete,))
        continuous = _array_attr(optimizer, "_continuous_idx", (n - n_discrete,))
        indices = np.concatenate([discrete, continuous])
        if sorted(indices.tolist()) != list(range(n)):
            raise ValueError("the discrete and continuous dimensions of CMAwM do not match")
        _array_attr(optimizer, "_continuous_space", (n - n_discrete, 2))
    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            point = copy.deepcopy(optimizer).ask()
    except (ArithmeticError, ValueError, IndexError, TypeError, np.linalg.LinAlgError) as err:
        raise ValueError(f"it cannot ask a point ({type(err).__name__}: {err})") from err
    x = point[0] if isinstance(point, tuple) else point
    if np.shape(x) != (n,) or not np.all(np.isfinite(x)):
        raise ValueError("it asks a point that is not finite")


def _int_attr(owner: object, name: str, low: int, high: int | None = None) -> int:
    """An integer attribute within ``[low, high]`` (``ValueError`` otherwise)."""
    value = getattr(owner, name, None)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} is not an integer ({type(value).__name__})")
    if value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise ValueError(f"{name} is {value}, not {bound}")
    return int(value)


def _real_attr(owner: object, name: str, *, positive: bool = False) -> float:
    """A finite real attribute, positive if asked (``ValueError`` otherwise)."""
    value = getattr(owner, name, None)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
        raise ValueError(f"{name} is not a number ({type(value).__name__})")
    if not math.isfinite(float(value)) or (positive and value <= 0):
        raise ValueError(f"{name} is {value}, not a finite{' positive' if positive else ''} number")
    return float(value)


def _array_attr(
    owner: object, name: str, shape: tuple[int, ...], *, optional: bool = False
) -> np.ndarray:
    """A finite numeric array attribute of ``shape`` (``ValueError`` otherwise)."""
    value = getattr(owner, name, None)
    if value is None and optional:
        return np.empty(0)
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iuf":
        raise ValueError(f"{name} is not a numeric array ({type(value).__name__})")
    if value.shape != shape:
        raise ValueError(f"{name} has shape {value.shape}, not {shape}")
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{name} holds a value that is not finite")
    return value


def _encode(value: Any) -> Any:
    """One value of an optimizer's state as JSON types (see `optimizer_state`)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int) and not isinstance(value, np.integer):
        return value
    if isinstance(value, float) and not isinstance(value, np.floating):
        return value if math.isfinite(value) else {"__float__": repr(value)}
    if isinstance(value, (np.ndarray, np.generic)):
        array = np.asarray(value)
        if array.dtype.kind not in _ARRAY_KINDS:
            raise TypeError(f"cannot store an array of dtype {array.dtype} as plain data")
        return {
            "__ndarray__": base64.b64encode(np.ascontiguousarray(array).tobytes()).decode(),
            "dtype": array.dtype.str,
            "shape": list(array.shape),
            "scalar": isinstance(value, np.generic),
        }
    if isinstance(value, (list, tuple)):
        return {"__list__": [_encode(v) for v in value], "tuple": isinstance(value, tuple)}
    if isinstance(value, np.random.RandomState):
        return {"__random_state__": _encode(value.get_state(legacy=True))}
    if type(value) in _OPTIMIZER_CLASSES.values():
        return {
            "__cmaes__": type(value).__name__,
            "attrs": {str(k): _encode(v) for k, v in vars(value).items()},
        }
    raise TypeError(f"cannot store a {type(value).__name__} as plain data")


def _decode(value: Any) -> Any:
    """Inverse of `_encode`; raises ``ValueError`` for anything else."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if not isinstance(value, dict):
        raise ValueError(f"unexpected {type(value).__name__} in a stored CMA-ES state")
    try:
        if "__float__" in value:
            text = str(value["__float__"])
            if text not in ("inf", "-inf", "nan"):
                raise ValueError(f"unexpected float {text!r}")
            return float(text)
        if "__ndarray__" in value:
            dtype = np.dtype(str(value["dtype"]))
            if dtype.kind not in _ARRAY_KINDS:
                raise ValueError(f"unexpected dtype {dtype}")
            shape = tuple(int(n) for n in value["shape"])
            raw = base64.b64decode(str(value["__ndarray__"]), validate=True)
            array = np.frombuffer(raw, dtype=dtype).reshape(shape).copy()
            return array[()] if value.get("scalar") else array
        if "__list__" in value:
            items = [_decode(v) for v in value["__list__"]]
            return tuple(items) if value.get("tuple") else items
        if "__random_state__" in value:
            rng = np.random.RandomState()
            rng.set_state(_decode(value["__random_state__"]))
            return rng
        if "__cmaes__" in value:
            cls = _OPTIMIZER_CLASSES.get(str(value["__cmaes__"]))
            if cls is None:
                raise ValueError(f"unknown optimizer class {value['__cmaes__']!r}")
            optimizer = cls.__new__(cls)
            optimizer.__dict__.update({str(k): _decode(v) for k, v in dict(value["attrs"]).items()})
            return optimizer
    except (KeyError, TypeError) as error:
        raise ValueError(f"malformed stored CMA-ES state: {error}") from error
    raise ValueError(f"unexpected keys {sorted(value)} in a stored CMA-ES state")


def _join_chunks(chunks: Mapping[str, Any], prefix: str) -> str:
    """The text split over ``{prefix}0``, ``{prefix}1``, ... (in index order)."""
    return "".join(str(chunks[f"{prefix}{i}"]) for i in range(len(chunks)))


def _derive_seed(*keys: int) -> int:
    """A 31-bit seed from integer keys (``numpy.random.SeedSequence`` mixes them)."""
    entropy = [k % 2**32 for k in keys]  # SeedSequence needs non-negative entropy
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] % (2**31 - 1))


def _is_compatible(trans: _SearchSpaceTransform, search_space: dict[str, BaseDistribution]) -> bool:
    """Whether ``search_space`` has exactly the parameters of ``trans``."""
    names = set(trans._search_space.keys())
    return names == set(search_space.keys())


def has_discrete_genes(search_space: Mapping[str, BaseDistribution]) -> bool:
    """Whether ``search_space`` has an integer or stepped gene on a linear scale with more than
    one value (what CMA-ES with Margin rounds inside the search)."""
    return any(
        isinstance(d, (IntDistribution, FloatDistribution))
        and d.step is not None
        and not d.log
        and not d.single()
        for d in search_space.values()
    )


def _check_popsize(popsize: int | None) -> None:
    """Raise ``ValueError`` unless ``popsize`` is ``None`` or an integer >= 2."""
    if popsize is None:
        return
    if isinstance(popsize, bool) or not isinstance(popsize, (int, np.integer)):
        raise ValueError(f"popsize must be an integer >= {_MIN_POPSIZE} or None, got {popsize!r}.")
    if popsize < _MIN_POPSIZE:
        raise ValueError(
            f"popsize must be >= {_MIN_POPSIZE} (CMA-ES needs mu >= 1), got {popsize}."
        )


def make_sampler(
    name: SamplerName,
    *,
    seed: int | None = None,
    restart: RestartStrategy = "none",
    popsize: int | None = None,
    inc_popsize: int = 2,
    consider_pruned_trials: bool = False,
    search_space: Mapping[str, BaseDistribution] | None = None,
    x0: Mapping[str, float] | None = None,
) -> BaseSampler:
    """Build the outer-loop sampler by name.

    Args:
        name: ``"cmaes"`` ([`RestartCmaEsSampler`][ermrl.search.RestartCmaEsSampler]), ``"tpe"``
            (`optuna.samplers.TPESampler`) or ``"random"``
            (`optuna.samplers.RandomSampler`).
        seed: Random seed.
        restart: CMA-ES restart strategy; only ``"none"`` is allowed for other samplers.
        popsize: Initial CMA-ES population size (``None``: ``cmaes`` default); only for
            ``"cmaes"``.
        inc_popsize: Population-size multiplier per large restart (>= 2); only used by
            ``"cmaes"``.
        consider_pruned_trials: ``"cmaes"`` only: a PRUNED trial counts as a member of its
            generation with its last intermediate value (turn it on with a pruner: otherwise a
            generation waits for ``popsize`` COMPLETE trials, and a study whose trials are mostly
            pruned hardly moves). TPE uses pruned trials on its own; random search ignores them.
        search_space: ``"cmaes"`` only: the fixed search space, so that CMA-ES samples from the
            first trial on (see [`RestartCmaEsSampler`][ermrl.search.RestartCmaEsSampler]); with an
            integer gene, CMA-ES searches with margin (rounding inside the search).
        x0: ``"cmaes"`` only: the start point of the first run (``None``: the box centre).

    Returns:
        The sampler.

    Raises:
        ValueError: For an unknown sampler or restart strategy, a restart strategy or popsize
            given with a sampler other than ``"cmaes"``, ``popsize < 2`` or ``inc_popsize < 2``.
    """
    if name not in SAMPLERS:
        raise ValueError(f"Unknown sampler {name!r}; expected one of {SAMPLERS}.")
    if restart not in RESTART_STRATEGIES:
        raise ValueError(
            f"Unknown restart strategy {restart!r}; expected one of {RESTART_STRATEGIES}."
        )
    _check_popsize(popsize)
    if isinstance(inc_popsize, bool) or not isinstance(inc_popsize, int) or inc_popsize < 2:
        raise ValueError(f"inc_popsize must be an integer >= 2, got {inc_popsize!r}.")
    if name != "cmaes":
        if restart != "none":
            raise ValueError(
                f"restart={restart!r} is only supported by the 'cmaes' sampler, not {name!r}."
            )
        if popsize is not None:
            raise ValueError(f"popsize is only supported by the 'cmaes' sampler, not {name!r}.")
    if name == "cmaes":
        with warnings.catch_warnings():
            # consider_pruned_trials is marked experimental in Optuna.
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return RestartCmaEsSampler(
                restart_strategy=restart,
                popsize=popsize,
                inc_popsize=inc_popsize,
                seed=seed,
                consider_pruned_trials=consider_pruned_trials,
                search_space=search_space,
                x0=x0,
            )
    if name == "tpe":
        return TPESampler(seed=seed)
    return RandomSampler(seed=seed)


def _detect_prefix(system_attrs: dict[str, Any]) -> str | None:
    for prefix in _ATTR_PREFIXES:
        if prefix + "n_restarts" in system_attrs:
            return prefix
    return None


def cma_generation_info(study: optuna.Study) -> list[dict[str, Any]]:
    """CMA-ES run/generation of every COMPLETE trial, e.g. for a fitness-per-generation plot.

    Args:
        study: A study optimized (at least partly) with
            [`RestartCmaEsSampler`][ermrl.search.RestartCmaEsSampler].

    Returns:
        One dict per COMPLETE trial, ordered by trial number, with keys:

        * ``"number"`` (int): trial number.
        * ``"value"`` (float | None): objective value (``None`` for multi-objective studies).
        * ``"restart"`` (int | None): restart index of the CMA-ES run (0 = first run).
        * ``"generation"`` (int | None): generation within that run.
        * ``"global_generation"`` (int | None): 0-based rank of ``(restart, generation)``
            among the pairs present, i.e. a generation counter running across restarts.
        * ``"popsize"`` (int | None): population size of that run.
        * ``"regime"`` (str | None): ``"large"`` or ``"small"`` (BIPOP regime).

        The CMA-ES fields are ``None`` for trials not sampled by CMA-ES (startup / first trial
        / independent fallback). ``pandas.DataFrame(rows)`` turns the result into a table.
    """
    rows: list[dict[str, Any]] = []
    for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        attrs = t.system_attrs
        prefix = _detect_prefix(attrs)
        value = t.values[0] if t.values is not None and len(t.values) == 1 else None
        row: dict[str, Any] = {
            "number": t.number,
            "value": value,
            "restart": None,
            "generation": None,
            "global_generation": None,
            "popsize": None,
            "regime": None,
        }
        if prefix is not None:
            restart = int(attrs[prefix + "n_restarts"])
            generation = attrs.get(f"{prefix}restart_{restart}:generation")
            popsize = attrs.get(prefix + "popsize")
            row.update(
                restart=restart,
                generation=None if generation is None else int(generation),
                popsize=None if popsize is None else int(popsize),
                regime=attrs.get(prefix + "regime"),
            )
        rows.append(row)
    rows.sort(key=lambda r: r["number"])

    pairs = sorted({(r["restart"], r["generation"]) for r in rows if r["generation"] is not None})
    rank = {pair: i for i, pair in enumerate(pairs)}
    for r in rows:
        if r["generation"] is not None:
            r["global_generation"] = rank[(r["restart"], r["generation"])]
    return rows
