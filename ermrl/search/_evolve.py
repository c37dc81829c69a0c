"""The outer loop: an Optuna study that proposes reservoirs and records their fitness.

One call of [`run_evolution`][ermrl.search.run_evolution] is one *worker*. Any number of workers
(processes, machines, SLURM array tasks) may share a study:

- **Exact budget.** ``n_trials`` is the study's total of COMPLETE, PRUNED, RUNNING and WAITING
  trials. A worker *claims* a trial (counts, then ``study.ask()``) under the storage's
  inter-process lock ([`ermrl.storage.study_lock`][ermrl.storage.study_lock]), so the workers never
  overshoot.
- **Dead workers.** RUNNING trials send heartbeats. Before each claim, a worker fails the trials
  whose heartbeat stopped (``grace_period``) and queues a WAITING copy with the same parameters
  ([`ermrl.storage.RetryStaleTrial`][ermrl.storage.RetryStaleTrial]), which the next claim picks up.
  When the budget is reached while other workers' trials still run, a worker waits for them, so that
  a trial whose worker died is still retried.
- **Interruptions.** SIGTERM (SLURM time limit, preemption), Ctrl-C or an error of the program
  closes the running trials as FAIL, queues a retry of each (the reference trial first) and
  raises ([`Interrupted`][ermrl.search.Interrupted] on SIGTERM, ``KeyboardInterrupt`` on Ctrl-C).
  Signals that arrive while a worker talks to the storage are handled right after, so a claim or a
  ``tell`` is never cut in half.

Re-running the same command resumes the study.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import optuna
from optuna.storages._heartbeat import BaseHeartbeat, get_heartbeat_thread, is_heartbeat_enabled
from optuna.trial import FrozenTrial, TrialState

from ermrl._progress import ProgressMode
from ermrl._text import plural
from ermrl.agents import NoEpisodeFinished, TrainingDiverged
from ermrl.config import EncoderConfig, EvolveConfig
from ermrl.search._claim import (
    Claim,
    claim_trial,
    close_interrupted,
    n_counted,
    record,
    requeue_lost_reference,
    retry_policy,
)
from ermrl.search._generalization import generalization_generation
from ermrl.search._objective import (
    EvaluateFn,
    EvaluateGenerationFn,
    FitnessResult,
    SeedRunner,
    decode_candidate,
    evaluate_encoder,
    evaluate_encoders,
)
from ermrl.search._progress import CANDIDATE_ATTR, best_trial, trial_line
from ermrl.search._pruning import pruning_reporter
from ermrl.search._signals import SignalGuard
from ermrl.search._study import REFERENCE_ATTR
from ermrl.storage import RetryStaleTrial

__all__ = [
    "EvaluateFn",
    "EvaluateGenerationFn",
    "EvolutionSummary",
    "PopulationWarning",
    "cma_popsize",
    "default_popsize",
    "generation_size",
    "run_evolution",
]


class PopulationWarning(UserWarning):
    """More workers evaluate a study at once than the CMA-ES population size."""


@dataclass
class EvolutionSummary:
    """What one worker did.

    Attributes:
        trials_run: Trials this worker started.
        completed: Trials it completed.
        failed: Trials it marked FAIL (diverged, no episode, interrupted).
        pruned: Trials pruned.
        best_value: The study's best fitness at the end (``None`` if no trial completed).
        best_params: Its parameters.
    """

    trials_run: int = 0
    completed: int = 0
    failed: int = 0
    pruned: int = 0
    best_value: float | None = None
    best_params: dict[str, float] | None = None


_FIRST_POLL = 0.5  # seconds between the first claims while waiting for other workers' trials


def cma_popsize(config: EvolveConfig) -> int | None:
    """The first CMA-ES population size of a run (``None`` for other samplers)."""
    if config.search.sampler != "cmaes":
        return None
    if config.search.popsize is not None:
        return config.search.popsize
    return default_popsize(config)


def default_popsize(config: EvolveConfig) -> int:
    """CMA-ES's default population size, 4 + 3 ln(dimension)."""
    return 4 + math.floor(3 * math.log(len(config.space.param_names)))


def generation_size(config: EvolveConfig) -> int:
    """Candidates the population backend trains together: the CMA-ES population size (the
    same default formula, or ``--popsize``, for the other samplers)."""
    if config.search.popsize is not None:
        return config.search.popsize
    return default_popsize(config)


def _popsize_message(popsize: int, workers: int, what: str) -> str:
    return (
        f"{what} {workers} but the CMA-ES population size is {popsize}: a generation is told "
        f"its first {popsize} COMPLETE trials, so the others are evaluated for little use. "
        f"Pass --popsize {workers} or more, or run at most {popsize} workers"
    )


def run_evolution(
    config: EvolveConfig,
    study: optuna.Study,
    *,
    quiet: bool = False,
    stream: TextIO | None = None,
    evaluate: EvaluateFn | None = None,
    wait_for_running: bool = True,
    requeue_interrupted: bool = True,
    n_workers: int | None = None,
    queued_only: bool = False,
    evaluate_generation: EvaluateGenerationFn | None = None,
    progress: ProgressMode = "none",
    callbacks: Sequence[Callable[[optuna.Study, FrozenTrial], None]] = (),
    tensorboard: str | Path | None = None,
) -> EvolutionSummary:
    """Run trials until the study holds ``config.search.n_trials`` counted trials.

    COMPLETE, PRUNED, RUNNING and WAITING trials count towards the budget, and trials are claimed
    under the storage's lock, so several workers sharing a study stop together at exactly the
    budget. A trial whose training diverges (NaN) or finishes no episode is marked FAIL and the
    worker goes on (a FAIL trial does not count: another one replaces it), unless its last
    ``n_trials`` trials all failed (a broken problem must not loop forever). Ctrl-C, SIGTERM or
    an error of the program marks the running trials FAIL, queues a retry of each with the same
    parameters (the reference trial first) and re-raises (SIGTERM as
    [`Interrupted`][ermrl.search.Interrupted]). Nothing is lost either way. A reference trial whose
    every run was cut short (by an older ermrl, or with its retries spent) is queued again when a
    worker starts.

    Args:
        config: The run's configuration.
        study: A study from [`create_or_resume_study`][ermrl.search.create_or_resume_study].
        quiet: No progress lines.
        stream: Where progress lines go (default ``sys.stdout``).
        evaluate: Fitness of a candidate, called as ``evaluate(encoder, runner, report)`` with
            the encoder settings decoded from the sampled point
            (default: [`evaluate_encoder`][ermrl.search.evaluate_encoder] on ``config.problem``; the
            generalization pipeline passes a multi-task fitness).
        wait_for_running: When the budget is reached but trials of other workers still run, wait
            for them (with heartbeats on): a trial whose worker died is then failed and retried
            here, and the study ends with ``n_trials`` finished trials.
        requeue_interrupted: Queue a WAITING copy of a trial cut short by a signal or an error
            (within the storage's ``max_retry``).
        n_workers: Workers expected to share the study, for the population-size warning
            (default: ``SLURM_ARRAY_TASK_COUNT`` when set).
        queued_only: Run only queued (WAITING) trials, never ask the sampler for a new point
            (re-evaluation: a failed candidate is not replaced by a random one).
        evaluate_generation: With the population backend, the fitness of a whole generation,
            ``evaluate_generation(encoders, runner)`` -> one fitness or exception per candidate
            (default: `evaluate_encoders` on ``config.problem``, or the
            multi-task fitness of a generalization config).
        progress: ``"lines"``: inside a trial (or generation), each run or population prints
            a line every tenth of its steps or 30 s with its rate and ETA; ``"bar"``: a live bar
            instead (`ermrl._progress`; the commands' default on a terminal); ``"none"``:
            one line per finished trial only. ``quiet`` silences all three.
        callbacks: Called as ``callback(study, trial)`` with each trial this worker recorded
            (COMPLETE, PRUNED or FAIL), as `optuna.study.Study.optimize` calls its
            callbacks: e.g. optuna-integration's ``WeightsAndBiasesCallback``.
        tensorboard: Each trial's runs also log training curves for TensorBoard under
            ``<tensorboard>/trial_<n>/seed_<s>`` (SB3's ``tensorboard_log``; a trial on several
            tasks: ``trial_<n>/<env_id>/seed_<s>``); ``None``: no logs.

    Returns:
        What this worker did.

    Raises:
        Interrupted: SIGTERM arrived (the running trial was closed).
        KeyboardInterrupt: Ctrl-C (the running trial was closed).
    """
    out = stream or sys.stdout
    say = _printer(quiet, out)
    heartbeats, poll = _heartbeat_poll(study)
    retry = retry_policy(study) if requeue_interrupted else None
    popsize = _warn_expected_workers(config, n_workers)  # None once warned
    todo = _queue_pending(config, study, queued_only, say)
    guard = SignalGuard()
    generation, evaluate_generation = _generation_fitness(config, evaluate_generation, quiet, out)
    runner = SeedRunner(
        config.n_procs, progress="none" if quiet else progress, stream=out, tensorboard=tensorboard
    )
    with runner, guard.installed():
        worker = _Worker(
            config, study, runner, guard, say, heartbeats=heartbeats, poll=poll, retry=retry,
            popsize=popsize, evaluate=evaluate, evaluate_generation=evaluate_generation,
            wait_for_running=wait_for_running, queued_only=queued_only, callbacks=callbacks,
        )  # fmt: skip
        worker.run(generation, announce=todo)
    worker.summary.best_value, _, worker.summary.best_params = best_trial(study)
    return worker.summary


def _printer(quiet: bool, out: TextIO) -> Callable[[str], None]:
    """A progress line printer: ``say(line)`` prints to ``out`` (nothing when ``quiet``)."""

    def say(line: str) -> None:
        if not quiet:
            print(line, file=out, flush=True)

    return say


def _heartbeat_poll(study: optuna.Study) -> tuple[bool, float]:
    """Whether the study's storage takes heartbeats, and the longest pause between claims.

    Waiting for other workers' trials at the end: a claim is cheap, so a worker polls at 0.5 s
    first (a trial about to end is seen at once) and backs off to at most half the heartbeat
    interval (0.5 to 5 s) for long waits.
    """
    storage = study._storage
    heartbeats = is_heartbeat_enabled(storage)
    interval = 1.0
    if heartbeats and isinstance(storage, BaseHeartbeat):  # always one when heartbeats is True
        interval = float(storage.get_heartbeat_interval() or 1)
    return heartbeats, min(max(interval / 2, 0.5), 5.0)


def _warn_expected_workers(config: EvolveConfig, n_workers: int | None) -> int | None:
    """Warn when more workers are expected than the CMA-ES population size.

    Args:
        config: The run's configuration.
        n_workers: Workers expected (default: ``SLURM_ARRAY_TASK_COUNT`` when set).

    Returns:
        The population size the worker still warns about when too many trials run at once
        (``None``: warned here already, or not CMA-ES).
    """
    popsize = cma_popsize(config)
    expected = n_workers or int(os.environ.get("SLURM_ARRAY_TASK_COUNT", "0") or 0)
    if popsize is not None and expected > popsize:
        warnings.warn(
            _popsize_message(popsize, expected, "this study expects up to"),
            PopulationWarning,
            stacklevel=3,  # run_evolution's caller
        )
        return None
    return popsize


def _queue_pending(
    config: EvolveConfig, study: optuna.Study, queued_only: bool, say: Callable[[str], None]
) -> bool:
    """Queue again a reference trial every run cut short; ``True`` when trials are left to run.

    Says so when the study already holds its budget and nothing is queued.
    """
    n_trials = config.search.n_trials
    done_before = n_counted(study)
    queued = len(study.get_trials(deepcopy=False, states=(TrialState.WAITING,)))
    if config.search.reference_trial and not queued_only:
        lost = requeue_lost_reference(study, config.space)
        if lost is not None:
            say(f"the reference trial #{lost} was cut short by every run; queued again")
            queued += 1
    if done_before >= n_trials and not queued:
        say(
            f"study {study.study_name!r} already has {done_before}/{n_trials} trials: nothing to do"
        )
    return done_before < n_trials or bool(queued)


def _generation_fitness(
    config: EvolveConfig,
    evaluate_generation: EvaluateGenerationFn | None,
    quiet: bool,
    out: TextIO,
) -> tuple[int | None, EvaluateGenerationFn | None]:
    """The generation size and a generation's fitness with the population backend.

    Args:
        config: The run's configuration.
        evaluate_generation: The caller's fitness of a generation (``None``: the problem's, or
            the multi-task fitness of a generalization config).
        quiet: No progress lines.
        out: Where progress lines go.

    Returns:
        ``(None, evaluate_generation)`` unchanged with another backend (trials one at a time).
    """
    if config.problem.ppo.backend != "population":
        return None, evaluate_generation
    generation = generation_size(config)
    if evaluate_generation is None and config.generalization is not None:
        evaluate_generation = generalization_generation(config, quiet=quiet, stream=out)
    elif evaluate_generation is None:
        problem = config.problem

        def evaluate_generation(
            encoders: Sequence[EncoderConfig], runner: SeedRunner
        ) -> list[FitnessResult | BaseException]:
            return evaluate_encoders(encoders, problem, runner=runner)

    return generation, evaluate_generation


def _announce(
    config: EvolveConfig,
    runner: SeedRunner,
    guard: SignalGuard,
    say: Callable[[str], None],
    generation: int | None,
) -> None:
    """Say how the trials will be trained (and start the process pool, which takes a while)."""
    problem = config.problem
    n_tasks = len(config.generalization.tasks) if config.generalization else 1
    if generation is not None:
        say(
            f"population backend: generations of up to {generation} candidates x "
            f"{plural(len(problem.seeds), 'seed')} = {generation * len(problem.seeds)} agents per task "
            f"({n_tasks} task(s)), trained in lockstep in "
            f"{min(config.n_procs, generation * len(problem.seeds))} process(es)"
        )
    elif config.n_procs > 1:
        n_runs = n_tasks * len(problem.seeds)
        with guard.deferred():
            size = runner.start(n_runs)
        say(
            f"{n_runs} training runs per trial on {config.n_procs} cores: "
            f"{size} single-threaded processes"
            + (
                " (more processes than cores keeps every core busy)"
                if size > config.n_procs
                else ""
            )
        )


class _Worker:
    """One worker of [`run_evolution`][ermrl.search.run_evolution], in named steps.

    A trial is *claimed* (`claim`), *trained* (`train`, or a whole generation with
    `train_generation`), *recorded* in the study (`record`) and *finished*: counted
    and reported (`finish`). When the budget is reached while other workers' trials run,
    the worker *waits* for them (`wait`). `run_trial` and `run_generation`
    chain the steps, with heartbeats on and signals deferred while the storage is written, and
    `run` repeats them until the worker stops.

    Args:
        config: The run's configuration.
        study: The study the worker claims trials from.
        runner: Trains the seeds of a candidate.
        guard: Defers signals while the storage is written.
        say: Prints a progress line (or nothing, quiet).
        heartbeats: Whether the storage takes heartbeats (waiting needs them).
        poll: The longest pause between claims while waiting for other workers.
        retry: Queues a retry of an interrupted trial (``None``: no retry).
        popsize: The CMA-ES population size to warn about (``None``: no warning is due).
        evaluate: The fitness hook of [`run_evolution`][ermrl.search.run_evolution] (``None``: the
            problem's).
        evaluate_generation: A generation's fitness (population backend).
        wait_for_running: Wait for other workers' trials when the budget is reached.
        queued_only: Claim only queued (WAITING) trials.
        callbacks: Called with each recorded trial (see
            [`run_evolution`][ermrl.search.run_evolution]).

    Attributes:
        summary: What this worker did so far.
    """

    def __init__(
        self,
        config: EvolveConfig,
        study: optuna.Study,
        runner: SeedRunner,
        guard: SignalGuard,
        say: Callable[[str], None],
        *,
        heartbeats: bool,
        poll: float,
        retry: RetryStaleTrial | None,
        popsize: int | None,
        evaluate: EvaluateFn | None,
        evaluate_generation: EvaluateGenerationFn | None,
        wait_for_running: bool,
        queued_only: bool,
        callbacks: Sequence[Callable[[optuna.Study, FrozenTrial], None]] = (),
    ) -> None:
        self.config = config
        self.study = study
        self.runner = runner
        self.guard = guard
        self.say = say
        self.heartbeats = heartbeats
        self.poll = poll
        self.retry = retry
        self.popsize = popsize
        self.evaluate = evaluate
        self.evaluate_generation = evaluate_generation
        self.wait_for_running = wait_for_running
        self.queued_only = queued_only
        self.callbacks = tuple(callbacks)
        self.n_trials = config.search.n_trials
        self.summary = EvolutionSummary()
        self.durations: list[float] = []  # seconds per trial, for the ETA
        self.pause = _FIRST_POLL  # before the next claim while waiting
        self.waiting_said = False
        self.failed_in_a_row = 0

    def run(self, generation: int | None, announce: bool) -> None:
        """Run trials (or whole generations of ``generation`` trials) until the worker stops.

        Args:
            generation: Trials trained together (population backend); ``None``: one at a time.
            announce: First say how the trials will be trained (trials are left to run).
        """
        if announce:
            _announce(self.config, self.runner, self.guard, self.say, generation)
        while True:
            self.guard.check()
            go_on = self.run_trial() if generation is None else self.run_generation(generation)
            if not go_on:
                break

    def claim(self) -> Claim:
        """Claim a trial under the storage's lock (``claim.trial is None``: none left)."""
        with self.guard.deferred():
            return claim_trial(
                self.study, self.config.space, self.n_trials, self.heartbeats, self.queued_only
            )

    def wait(self, claim: Claim) -> bool:
        """Budget reached: wait (``True``: claim again) while other workers' trials run."""
        if not (self.wait_for_running and self.heartbeats and claim.running > 0):
            return False
        if not self.waiting_said:
            self.say(
                f"budget reached; waiting for {claim.running} running trial(s) of "
                "other workers (a trial whose worker died is retried here)"
            )
            self.waiting_said = True
        time.sleep(self.pause)
        self.pause = min(self.pause * 1.5, self.poll)
        return True

    def train(self, claim: Claim, heartbeat: Any) -> tuple[TrialState, FitnessResult | None, str]:
        """Train one claimed trial: its state, fitness (``None`` unless trained) and note.

        A trial that diverges or finishes no episode is FAIL, a pruned one PRUNED. Anything
        else (a signal, a bug) closes the trial (`close_interrupted`) and is re-raised.
        """
        assert claim.trial is not None
        trial = claim.trial
        use_report = pruning_reporter(trial) if self.config.search.pruner != "none" else None
        state = TrialState.COMPLETE
        result: FitnessResult | None = None
        note = ""
        try:
            self.guard.check()  # a signal that arrived during the claim
            # The sampled point is a plain dict; the problem's encoder (or learner) decodes it.
            encoder, candidate = decode_candidate(
                self.config.space, claim.params, self.config.problem
            )
            if self.evaluate is None:
                result = evaluate_encoder(encoder, candidate, runner=self.runner, report=use_report)
            else:  # encoders' studies only (evolve-generalization, its re-evaluation)
                assert encoder is not None
                result = self.evaluate(encoder, self.runner, use_report)
            if not math.isfinite(result.fitness):
                raise TrainingDiverged(f"non-finite fitness {result.fitness}")
        except optuna.TrialPruned as err:
            state, note = TrialState.PRUNED, str(err)
        except (TrainingDiverged, NoEpisodeFinished) as err:
            state, note = TrialState.FAIL, str(err)
        except BaseException as err:
            close_interrupted(
                self.study, trial, err, self.guard, self.runner, heartbeat, self.say, self.retry
            )
            raise
        return state, result, note

    def train_generation(
        self, claims: Sequence[Claim], beats: Sequence[Any]
    ) -> list[FitnessResult | BaseException]:
        """Train claimed trials together (population backend): a fitness or a failure each.

        Anything but a divergence or an episode-less run (a signal, a bug) closes every trial
        (`close_interrupted`) and is re-raised.
        """
        try:
            self.guard.check()  # a signal that arrived during the claims
            encoders = []
            for c in claims:
                encoder = decode_candidate(self.config.space, c.params, self.config.problem)[0]
                assert encoder is not None  # the population backend trains encoders' studies
                encoders.append(encoder)
            assert self.evaluate_generation is not None
            results = self.evaluate_generation(encoders, self.runner)
            unexpected = next(
                (
                    r
                    for r in results
                    if isinstance(r, BaseException)
                    and not isinstance(r, (TrainingDiverged, NoEpisodeFinished))
                ),
                None,
            )
            if unexpected is not None:
                raise unexpected
        except BaseException as err:
            raised: BaseException | None = None
            # The reference's retry first: the next worker trains it before the others.
            order = sorted(zip(claims, beats), key=lambda cb: not _is_reference(cb[0]))
            for claim, beat in order:
                assert claim.trial is not None
                try:
                    close_interrupted(
                        self.study, claim.trial, err, self.guard, self.runner, beat, self.say,
                        self.retry,
                    )  # fmt: skip
                except BaseException as closing:  # noqa: BLE001 (re-raised below)
                    raised = raised or closing
            if raised is not None:
                raise raised from err
            raise
        return results

    def record(
        self,
        claim: Claim,
        state: TrialState,
        result: FitnessResult | None,
        note: str,
        elapsed: float,
    ) -> object:
        """Tell the study a trained trial's outcome (``None``: another worker closed it)."""
        assert claim.trial is not None
        self.durations.append(elapsed)
        return record(self.study, claim.trial, state, result, note)

    def finish(
        self,
        claim: Claim,
        closed: object,
        state: TrialState,
        result: FitnessResult | None,
        note: str,
        elapsed: float,
    ) -> bool:
        """Count and report a recorded trial; ``False`` when the worker must stop."""
        assert claim.trial is not None
        say, summary, n_trials = self.say, self.summary, self.n_trials
        if closed is None:
            say(
                f"[trial {claim.trial.number}] was closed by another worker (stale); result dropped"
            )
            return True
        if state == TrialState.COMPLETE:
            summary.completed += 1
            self.failed_in_a_row = 0
        elif state == TrialState.PRUNED:
            summary.pruned += 1
            self.failed_in_a_row = 0
        else:
            summary.failed += 1
            self.failed_in_a_row += 1
        counted = n_counted(self.study)
        remaining = max(n_trials - counted, 0)
        # A re-evaluation run is named by the evolution trial it re-trains.
        attrs = closed.user_attrs if isinstance(closed, FrozenTrial) else {}
        candidate = attrs.get(CANDIDATE_ATTR)
        eta = remaining * (sum(self.durations) / len(self.durations))
        say(
            trial_line(
                self.study, claim.trial.number, claim.params, state, result, note, elapsed,
                counted=counted, n_trials=n_trials, retry_of=claim.retry_of, eta=eta,
                candidate=candidate,
            )
        )  # fmt: skip
        for callback in self.callbacks:
            assert isinstance(closed, FrozenTrial)
            callback(self.study, closed)
        if self.failed_in_a_row >= n_trials:
            say(
                f"stopping: the last {plural(self.failed_in_a_row, 'trial')} of this worker failed "
                "(FAIL trials do not count towards the budget; is the problem broken?)"
            )
            return False
        return True

    def run_trial(self) -> bool:
        """Claim, train, record and finish one trial, or wait; ``False`` when the worker must
        stop."""
        # A signal between the claim and the training is raised inside train(), which closes
        # the trial and queues it again (raised here, it would leave the trial RUNNING).
        with self.guard.deferred():
            claim = self.claim()
            if claim.trial is not None:
                heartbeat = get_heartbeat_thread(claim.trial._trial_id, self.study._storage)
                heartbeat.start()
        if claim.trial is None:
            return self.wait(claim)
        self.pause = _FIRST_POLL
        if self.popsize is not None and claim.running > self.popsize:
            warnings.warn(
                _popsize_message(self.popsize, claim.running, "trials running at once:"),
                PopulationWarning,
                stacklevel=4,  # run_evolution's caller (through run())
            )
            self.popsize = None  # warned once
        self.summary.trials_run += 1
        started = time.perf_counter()
        self.runner.label = f"trial {claim.trial.number}"
        self.runner.trial = claim.trial.number
        try:
            state, result, note = self.train(claim, heartbeat)
        except BaseException:
            heartbeat.join()  # a running heartbeat thread would keep the process from exiting
            raise
        with self.guard.deferred():
            heartbeat.join()
            elapsed = time.perf_counter() - started
            closed = self.record(claim, state, result, note, elapsed)
        return self.finish(claim, closed, state, result, note, elapsed)

    def run_generation(self, size: int) -> bool:
        """Claim up to ``size`` trials, train them together, record and finish each (population
        backend), or wait; ``False`` when the worker must stop."""
        claims: list[Claim] = []
        last: Claim | None = None
        beats = []
        # A signal during the claims is raised inside train_generation(), which closes every
        # claimed trial and queues it again (raised here, it would leave them RUNNING).
        with self.guard.deferred():
            try:
                for _ in range(size):
                    last = self.claim()
                    if last.trial is None:
                        break
                    claims.append(last)
                    beats.append(get_heartbeat_thread(last.trial._trial_id, self.study._storage))
                    beats[-1].start()
            except BaseException:
                _join(beats)  # a running heartbeat thread would keep the process from exiting
                raise
        if not claims:
            assert last is not None
            return self.wait(last)
        self.pause = _FIRST_POLL
        self.summary.trials_run += len(claims)
        started = time.perf_counter()
        numbers = [c.trial.number for c in claims if c.trial is not None]
        self.runner.label = (
            f"trial {numbers[0]}" if len(numbers) == 1 else f"trials {numbers[0]}-{numbers[-1]}"
        )
        self.runner.trials = tuple(numbers)  # each candidate's runs' TensorBoard folders
        try:
            results = self.train_generation(claims, beats)
        except BaseException:
            _join(beats)
            raise
        outcomes = []
        with self.guard.deferred():
            for beat in beats:
                beat.join()
            elapsed = (time.perf_counter() - started) / len(claims)
            for claim, outcome in zip(claims, results):
                result = outcome if isinstance(outcome, FitnessResult) else None
                state, note = TrialState.COMPLETE, ""
                if result is None:
                    state, note = TrialState.FAIL, str(outcome)
                elif not math.isfinite(result.fitness):
                    state, note = TrialState.FAIL, f"non-finite fitness {result.fitness}"
                closed = self.record(claim, state, result, note, elapsed)
                outcomes.append((claim, closed, state, result, note))
        go_on = [self.finish(*outcome, elapsed) for outcome in outcomes]  # report every trial
        return all(go_on)


def _join(beats: list[Any]) -> None:
    """Stop the heartbeat threads of trials a worker leaves on an error (non-daemon threads:
    the process would wait for them forever at exit)."""
    for beat in beats:
        beat.join()


def _is_reference(claim: Claim) -> bool:
    return claim.trial is not None and bool(claim.trial.user_attrs.get(REFERENCE_ATTR))
