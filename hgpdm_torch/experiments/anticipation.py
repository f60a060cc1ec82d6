r"""Anticipatory action selection in simulated table tennis (thesis Sec. 4.3, Fig. 4.6 and 4.7).

Protocol (Sec. 4.3.1-4.3.2, adapted where noted):

1. ``num_trials`` opponent strokes (:func:`~hgpdm_torch.robots.table_tennis.trials.make_trials`)
   and the reward of every movement (forehand, middle, backhand) started at every decision time
   (320, 240, 160, 80, 0 ms before the opponent's hit) from the SAPIEN scene
   (:func:`~hgpdm_torch.robots.table_tennis.trials.reward_table`, +1 return / -1 miss).
   Trials outside the robot's overall hitting region are excluded; here a trial is inside when
   some movement started at some time returns the ball.
2. Ten-fold cross-validation. Per fold an IDDM (continuous target g, linear measurement kernel)
   is fitted on training strokes, and the online filter (Algorithm 3.2, predictive evidence) gives
   every trial's belief after the observations available at each decision time: latent mean and
   covariance plus the histogram over a grid of targets (:func:`~hgpdm_torch.decision.stopping.
   belief_vector`). Radial basis features (Eq. 37) use K-means centres of the training beliefs.
3. Methods, scored by the successful returns on the held-out fold, summed over folds:
   each single movement started 240 ms before the hit; oracle timing (the best movement by the
   learned stopping values, always chosen at 240/160/80 ms); NAC; LSPI (Algorithm 4.1); MCP
   (Algorithms 4.2-4.3 with LSPI's stopping values) -- all learned from the enumerated training
   episodes (Fig. 4.6); and LSPI vs MCP learned from 1, 2, 5, 10 episodes per training trial
   sampled with the uniform exploration policy (Fig. 4.7).
4. The whole cross-validation is repeated ``repetitions`` times and reported as mean +- SEM.
   The thesis repeats it to average over the robot's randomness; the SAPIEN scene here is
   deterministic, so the folds (and the IDDM of each fold) are fixed and the repetitions average
   over the learning algorithms' randomness (sampled episodes, NAC, MCP particles).
   Deterministic methods therefore have zero SEM.

:func:`run_protocol` takes the observations and reward table directly (testable without the
simulator); :func:`run_experiment` simulates them first; :func:`main` is the CLI. The belief
fitting and the policies it compares are library code in :mod:`hgpdm_torch.decision.beliefs` and
:mod:`hgpdm_torch.decision.policies`.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch

from ..crossval import held_out
from ..decision.beliefs import Beliefs, decision_indices, fit_beliefs
from ..decision.lspi import lspi
from ..decision.mcp import WAIT_VALUES, EarlyStopping
from ..decision.nac import nac
from ..decision.policies import (
    blind_choice,
    choose_source,
    fixed_time_choice,
    fixed_time_policy,
    greedy_policy,
    learn_stopping,
    mcp_policy,
    planning_policy,
    stop_only_q,
)
from ..decision.sources import FEATURES, PLAYER_SOURCES, SELECTABLE_SOURCES, track_beliefs
from ..decision.stopping import ACTIONS, Episodes, StoppingProblem
from ..models import supervised_init
from ..parallel import Executor
from ..results import ResultTable
from ..validation import as_tensor, check_choice
from .arguments import (
    add_executor_arguments,
    check_output_files,
    connect,
    int_at_least,
    output_folder,
    positive_int,
    random_seed,
    smoke_run,
)
from .dtype import float64_default

__all__ = [
    "AnticipationConfig",
    "add_common_arguments",
    "check_reward_cache",
    "connect",
    "learn_players",
    "main",
    "player_bars",
    "plot_results",
    "run_experiment",
    "run_protocol",
    "successes",
    "valid_trials",
    # moved to hgpdm_torch.decision (beliefs, policies); still importable from here
    "Beliefs",
    "decision_indices",
    "fit_beliefs",
    "fixed_time_policy",
    "greedy_policy",
    "mcp_policy",
    "stop_only_q",
]

MOVEMENTS = ACTIONS[1:]
ORACLE_TIMES = (-0.24, -0.16, -0.08)
SINGLE_TIME = -0.24
#: What ``hgpdm anticipation`` saves into ``--out``: the tables, then :func:`plot_results`'s.
_TABLES = ("fig4_6.json", "fig4_7.json")
_FIGURES = ("fig4_6_returns.png", "fig4_7_sample_efficiency.png")
BLIND = "best blind (training folds)"
"""The row of the best blind strategy (one movement at one start time) chosen on the training
folds."""
FIXED_TIME = "best fixed time (training folds)"
"""The row of the best fixed-time strategy (the belief's movement at one start time) chosen on
the training folds."""
BELIEFS = ("auto", *PLAYER_SOURCES)
"""``belief`` settings: ``"auto"`` (by cross-validated return rate among
:data:`~hgpdm_torch.decision.sources.SELECTABLE_SOURCES`) or one source a player may use."""


@dataclass(frozen=True)
class AnticipationConfig:
    """Sizes and settings of the experiment (defaults: the thesis's, Sec. 4.3).

    Attributes:
        num_trials: simulated strokes before exclusion (270).
        folds: cross-validation folds (10); repetitions: repeats of the cross-validation (10).
        episodes: sampled episodes per training trial for Fig. 4.7.
        iddm_trials: training strokes the IDDM of a fold is fitted on (all when larger).
        latent_dim, fit_steps, alpha, alpha_g: IDDM latent dimension, optimiser steps,
            transition kernel and g kernel. ``fit_steps`` is a budget: on the demo's 150
            watched strokes (seed 0) the MAP loss still falls after 60 L-BFGS steps (and after
            400), but the belief-mean error on 80 other strokes at 320, 240, 160, 80, 0 ms,
            43.0, 46.4, 44.0, 40.1, 26.5 cm at 60 steps, moved by -0.8, -3.3, -4.4, -0.8, +0.2
            cm at 150 steps (4x the time) and -0.8, -2.8, -2.6, -1.9, -0.2 cm at 400; each
            result reports its fits (``FitResult.summary``). The latents
            start from partial least squares on the training targets
            (:func:`~hgpdm_torch.models.supervised_init`), as in the target-prediction
            experiment (with PCA the latent keeps the ball's flight and loses the target).
        grid_size: K, targets in the belief histogram, evenly over +-grid_max.
        forgetting: the online filter's forgetting factor.
        belief: the players' belief source (:mod:`~hgpdm_torch.decision.sources`): ``"auto"``
            (per fold, the selectable source whose LSPI player returns most training strokes in
            a 3-fold cross-validation), ``"linear-iddm"``, ``"gp-iddm"`` (the thesis's) or
            ``"phase-gp-iddm"`` (the phase-aware GP IDDM, not among auto's candidates).
        features: decision features, ``"moments"`` (belief mean, sd and step;
            :class:`~hgpdm_torch.decision.basis.MomentBasis`) or ``"rbf"`` (the thesis's RBFs
            on the belief vector, Eq. 37).
        centres: RBF centres (100 in the thesis); ridge: LSPI's delta.
        particles: MCP budget per decision; confidence: its early-termination level.
        wait_value: how MCP values a particle of the next belief
            (:data:`~hgpdm_torch.decision.mcp.WAIT_VALUES`): ``"lspi"`` (default: the best
            LSPI value there, waiting included where the next step may wait) or ``"stop"`` (its
            best stopping value, Algorithm 4.2 as printed).
        nac_iterations, nac_episodes, nac_step: NAC updates, episodes per trial, step size.
        seed: seeds the trials and every random choice; workers: SAPIEN processes.
    """

    num_trials: int = 270
    folds: int = 10
    repetitions: int = 10
    episodes: tuple[int, ...] = (1, 2, 5, 10)
    iddm_trials: int = 80
    latent_dim: int = 6
    fit_steps: int = 60
    alpha: tuple[float, float, float, float] = (0.9, 0.3, 0.1, 1e-2)
    alpha_g: tuple[float, float] = (4.0, 0.1)
    grid_size: int = 25
    grid_max: float = 1.2
    forgetting: float = 0.1
    belief: str = "auto"
    features: str = "moments"
    centres: int = 100
    ridge: float = 1e-3
    particles: int = 500
    confidence: float = 0.99
    wait_value: str = "lspi"
    nac_iterations: int = 100
    nac_episodes: int = 4
    nac_step: float = 0.5
    seed: int = 0
    workers: int = 1

    @classmethod
    def smoke(cls, **changes: Any) -> AnticipationConfig:
        """A few-minute setting for CI (``HGPDM_SMOKE=1``) and the default CLI run."""
        base = dict(
            num_trials=24, folds=3, repetitions=2, episodes=(1, 5), iddm_trials=16, fit_steps=15,
            grid_size=13, centres=20, particles=200, nac_iterations=30,
        )  # fmt: skip
        return cls(**{**base, **changes})

    def __post_init__(self) -> None:
        for name in ("num_trials", "folds", "repetitions", "iddm_trials", "latent_dim"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if not 2 <= self.folds <= self.num_trials:
            raise ValueError(
                f"folds must be in [2, num_trials={self.num_trials}], got {self.folds}"
            )
        check_choice(self.belief, "belief", BELIEFS)
        check_choice(self.features, "features", FEATURES)
        check_choice(self.wait_value, "wait_value", WAIT_VALUES)
        if not self.episodes or any(
            isinstance(e, bool) or not isinstance(e, int) or e < 1 for e in self.episodes
        ):
            raise ValueError(f"episodes must be positive ints, got {self.episodes!r}")

    def initial_latents(self, obs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Initial IDDM latents ``[n T, latent_dim]`` of training strokes ``obs [n, T, Dz]`` with
        targets ``[n]``: partial least squares (:func:`~hgpdm_torch.models.supervised_init`); the
        initialisation :func:`~hgpdm_torch.decision.beliefs.fit_beliefs` asks its config for."""
        return supervised_init(obs, targets, self.latent_dim)


def valid_trials(rewards: torch.Tensor) -> torch.Tensor:
    """``[n]`` mask of trials inside the overall hitting region: some movement started at some
    time returns the ball (``rewards [n, S, T]``)."""
    rewards = as_tensor(rewards, "rewards", ndim=3)
    return (rewards > 0).flatten(1).any(1)


def successes(episodes: Episodes) -> int:
    """Number of successful returns among ``episodes``."""
    return int((episodes.reward > 0).sum())


def run_protocol(
    obs: torch.Tensor,
    obs_times: torch.Tensor,
    targets: torch.Tensor,
    rewards: torch.Tensor,
    start_times: tuple[float, ...],
    config: AnticipationConfig | None = None,
    *,
    executor: Executor | None = None,
    progress: bool = False,
) -> tuple[ResultTable, ResultTable]:
    """Cross-validated comparison of Sec. 4.3.2 on given trials.

    Args:
        obs: ``[n, T_obs, Dz]`` observations of each stroke before the hit.
        obs_times: ``[T_obs]`` their times relative to the hit [s].
        targets: ``[n]`` true targets (training labels of the IDDM).
        rewards: ``[n, 3, T]`` rewards of (forehand, middle, backhand) started at each time.
        start_times: ``T`` decision times relative to the hit [s], increasing; must include
            -0.24, -0.16 and -0.08 (single-movement and oracle-timing baselines).
        config: sizes and settings (default :class:`AnticipationConfig`).
        executor: run the folds (each with all its repetitions) on it
            (:func:`~hgpdm_torch.parallel.get_executor`: local processes or a Ray cluster); the
            tables are the serial run's, every random choice being seeded by ``config.seed``,
            the fold and the repetition. ``None``: in this process.
        progress: tqdm bar over the folds.

    Returns:
        The Fig. 4.6 table (successful returns per method, mean and SEM over repetitions, and the
        rate over the valid trials) and the Fig. 4.7 table (LSPI and MCP vs sampled episodes).
    """
    config = config or AnticipationConfig()
    obs = as_tensor(obs, "obs", ndim=3)
    targets = as_tensor(targets, "targets", ndim=1, dtype=obs.dtype)
    rewards = as_tensor(rewards, "rewards", ndim=3, dtype=obs.dtype)
    start_times = tuple(float(s) for s in start_times)
    if rewards.shape[1] != len(MOVEMENTS) or rewards.shape[2] != len(start_times):
        raise ValueError(
            f"rewards must have shape [n, {len(MOVEMENTS)}, {len(start_times)}], got "
            f"{tuple(rewards.shape)}"
        )
    if not (obs.shape[0] == targets.shape[0] == rewards.shape[0]):
        raise ValueError("obs, targets and rewards must describe the same n trials")
    missing = [
        s for s in (SINGLE_TIME, *ORACLE_TIMES) if not any(abs(s - x) < 1e-9 for x in start_times)
    ]
    if missing:
        raise ValueError(f"start_times must include {missing} for the baselines")
    steps_at = decision_indices(obs_times, start_times)
    step_of = {
        s: min(range(len(start_times)), key=lambda i: abs(start_times[i] - s))
        for s in (SINGLE_TIME, *ORACLE_TIMES)
    }

    valid = valid_trials(rewards)
    idx = torch.nonzero(valid).flatten()
    n = len(idx)
    if n < 2 * config.folds:
        raise ValueError(
            f"only {n} valid trials; need at least {2 * config.folds} for {config.folds} folds"
        )
    obs, targets, rewards = obs[idx], targets[idx], rewards[idx]
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(config.seed))
    fold_of = torch.empty(n, dtype=torch.long)
    fold_of[perm] = torch.arange(n) % config.folds

    candidates = SELECTABLE_SOURCES if config.belief == "auto" else (config.belief,)
    methods = _methods(candidates)
    counts = {m: torch.zeros(config.repetitions) for m in methods}
    sample_counts = {
        (a, e): torch.zeros(config.repetitions) for a in ("LSPI", "MCP") for e in config.episodes
    }

    start = time.perf_counter()
    job = partial(
        _fold, obs, targets, rewards, fold_of, steps_at, step_of, candidates, config,
    )  # fmt: skip
    folds = held_out(
        [() for _ in range(config.folds)], job, executor=executor, progress=progress,
        desc="anticipation",
    )  # fmt: skip
    fits, chosen, rates = {}, [], []
    for fold in folds:
        for src, src_fits in fold["fits"].items():
            fits.setdefault(src, []).extend(src_fits)
        chosen.append(fold["source"])
        rates.append(fold["rate"])
        for name, value in fold["counts"].items():
            counts[name] += value
        for key, value in fold["sample_counts"].items():
            sample_counts[key] += value
    meta = {**dataclasses.asdict(config), "valid trials": n,
            "seconds": time.perf_counter() - start, "belief used": chosen,
            "belief CV return rates": rates, "belief fits": fits}  # fmt: skip

    def stats(v: torch.Tensor) -> tuple[float, float]:
        sem = float(v.std() / v.numel() ** 0.5) if v.numel() > 1 else 0.0
        return float(v.mean()), sem

    fig6 = ResultTable(
        f"Fig. 4.6: successful returns of {n} valid trials ({config.folds}-fold CV x "
        f"{config.repetitions})",
        ["method", "returns", "SEM", "rate"],
        meta=meta,
    )
    for m in methods:
        mean, sem = stats(counts[m])
        fig6.add(method=m, returns=mean, SEM=sem, rate=mean / n)
    fig7 = ResultTable(
        f"Fig. 4.7: successful returns of {n} valid trials vs sampled episodes per training trial "
        "(uniform exploration)",
        ["episodes", "LSPI", "LSPI SEM", "MCP", "MCP SEM"],
        meta=meta,
    )
    for e in config.episodes:
        (lm, ls), (mm, ms) = stats(sample_counts[("LSPI", e)]), stats(sample_counts[("MCP", e)])
        fig7.add(**{"episodes": e, "LSPI": lm, "LSPI SEM": ls, "MCP": mm, "MCP SEM": ms})
    return fig6, fig7


def _methods(candidates: tuple[str, ...]) -> list[str]:
    """The rows of the Fig. 4.6 table for these belief sources."""
    methods = [f"single {m} @240ms" for m in MOVEMENTS]
    methods += [f"oracle timing @{int(round(-1000 * s))}ms" for s in ORACLE_TIMES]
    methods += [BLIND, FIXED_TIME, "NAC", "LSPI", "MCP"]
    return methods + [f"LSPI ({src} belief)" for src in candidates] + ["MCP (oracle belief)"]


def learn_players(
    vectors: dict[str, torch.Tensor],
    rewards: torch.Tensor,
    train: torch.Tensor,
    test: torch.Tensor,
    candidates: tuple[str, ...],
    features: str,
    config: AnticipationConfig,
) -> tuple[str, dict[str, float], dict[str, tuple[StoppingProblem, StoppingProblem, Any, Any]]]:
    """One fold's learned players, for this protocol and ``hgpdm demo``: the belief source
    chosen on the training strokes ``train`` (:func:`~hgpdm_torch.decision.policies.
    choose_source`, with its CV return rates) and, for each of ``candidates`` and the oracle,
    ``(training problem, test problem, state features, LSPI's values)``
    (:func:`~hgpdm_torch.decision.policies.learn_stopping` on the training strokes).

    Args:
        vectors: belief source -> ``[n, T, F]`` belief vectors of all ``n`` strokes.
        rewards: ``[n, S, T]`` reward table of the strokes.
        train: indices of the fold's training strokes.
        test: indices of its test strokes.
        candidates: the sources to choose from.
        features: the state features, ``"moments"`` or ``"rbf"``.
        config: ``centres``, ``ridge`` and ``seed`` of the players.
    """
    options = {"centres": config.centres, "ridge": config.ridge, "seed": config.seed}
    source, cv = choose_source({s: v[train] for s, v in vectors.items()}, rewards[train],
                               candidates, features, **options)  # fmt: skip
    learned = {}
    for src in (*candidates, "oracle"):
        problem = StoppingProblem(vectors[src], rewards)
        train_p, test_p = problem.subset(train), problem.subset(test)
        learned[src] = (train_p, test_p, *learn_stopping(train_p, features, **options))
    return source, cv, learned


def _fold(
    obs: torch.Tensor,
    targets: torch.Tensor,
    rewards: torch.Tensor,
    fold_of: torch.Tensor,
    steps_at: list[int],
    step_of: dict[float, int],
    candidates: tuple[str, ...],
    config: AnticipationConfig,
    k: int,
) -> dict[str, Any]:
    """Fold ``k`` of :func:`run_protocol` with all its repetitions (module-level, so that it
    pickles to an executor; its randomness is seeded by ``config.seed``, the repetition and
    ``k``): the beliefs' fits, the source chosen with its CV return rate, and per method the
    ``[repetitions]`` successes on the fold's test trials."""
    counts = {m: torch.zeros(config.repetitions) for m in _methods(candidates)}
    sample_counts = {
        (a, e): torch.zeros(config.repetitions) for a in ("LSPI", "MCP") for e in config.episodes
    }
    rule = EarlyStopping(config.particles, config.confidence, min(100, config.particles))
    fits: dict[str, list] = {}
    train = torch.nonzero(fold_of != k).flatten()
    test = torch.nonzero(fold_of == k).flatten()
    tracks = {  # clip: the oracle's reference belief of a return just beyond the grid
        src: track_beliefs(src, obs[train], targets[train], obs, targets, steps_at, config,
                           clip=True)
        for src in (*candidates, "oracle")
    }  # fmt: skip
    for src, track in tracks.items():
        fits.setdefault(src, []).extend(track.fits)
    # the training strokes' beliefs for choosing the source and learning the players come
    # from models that did not see them (2-fold cross-fitting within the training folds):
    # a model's beliefs on its own training strokes are better than on new ones, which
    # would favour the more flexible source and teach the players to trust it too much
    vectors = {}
    for src, track in tracks.items():
        v = track.vectors(config.features).clone()
        if src != "oracle":
            v[train] = _cross_fitted(src, obs, targets, steps_at, train, config)
        vectors[src] = v
    source, cv, learned = learn_players(
        vectors, rewards, train, test, candidates, config.features, config
    )
    train_p, test_p, basis, q = learned[source]
    # deterministic methods: the same in every repetition
    fixed = {}
    for a, name in enumerate(MOVEMENTS):
        fixed[f"single {name} @240ms"] = int((test_p.rewards[:, a, step_of[SINGLE_TIME]] > 0).sum())
    for s in ORACLE_TIMES:
        q_t = stop_only_q(train_p, step_of[s], basis, config.ridge)
        ep = test_p.run(fixed_time_policy(q_t, basis, step_of[s]))
        fixed[f"oracle timing @{int(round(-1000 * s))}ms"] = successes(ep)
    a, t = blind_choice(rewards[train])
    fixed[BLIND] = int((rewards[test, a, t] > 0).sum())
    step, q_t = fixed_time_choice(train_p, basis, config.ridge)
    fixed[FIXED_TIME] = successes(test_p.run(fixed_time_policy(q_t, basis, step)))
    fixed["LSPI"] = successes(test_p.run(greedy_policy(q, basis, test_p)))
    for src in candidates:
        _, tp, b, qs = learned[src]
        fixed[f"LSPI ({src} belief)"] = successes(tp.run(greedy_policy(qs, b, tp)))
    for r in range(config.repetitions):
        gen = torch.Generator().manual_seed(config.seed + 1000 * r + k)
        for name, value in fixed.items():
            counts[name][r] += value
        counts["MCP"][r] += successes(
            test_p.run(
                planning_policy(
                    tracks[source],
                    test,
                    q,
                    basis,
                    rule,
                    test_p.horizon,
                    config.features,
                    gen,
                    config.wait_value,
                )
            )
        )
        _, tp, b, qs = learned["oracle"]
        counts["MCP (oracle belief)"][r] += successes(
            tp.run(
                planning_policy(
                    tracks["oracle"],
                    test,
                    qs,
                    b,
                    rule,
                    tp.horizon,
                    config.features,
                    gen,
                    config.wait_value,
                )
            )
        )
        result = nac(
            train_p, basis(train_p.beliefs), iterations=config.nac_iterations,
            episodes_per_trial=config.nac_episodes, step_size=config.nac_step, generator=gen,
        )  # fmt: skip
        allowed = torch.stack([test_p.allowed(t) for t in range(test_p.horizon)])
        probs = result.policy.probs(basis(test_p.beliefs), allowed)
        # expected successes of the stochastic policy: (1 + E[r]) / 2 per trial
        counts["NAC"][r] += float(((1 + test_p.expected_reward(probs)) / 2).sum())
        for e in config.episodes:
            sampled = train_p.sample_episodes(e, generator=gen)
            q_e = lspi(train_p.transitions(sampled), features=basis, ridge=config.ridge).q
            sample_counts[("LSPI", e)][r] += successes(
                test_p.run(greedy_policy(q_e, basis, test_p))
            )
            sample_counts[("MCP", e)][r] += successes(test_p.run(planning_policy(
                tracks[source], test, q_e, basis, rule, test_p.horizon, config.features,
                gen, config.wait_value)))  # fmt: skip
    return {"fits": fits, "source": source, "rate": cv, "counts": counts,
            "sample_counts": sample_counts}  # fmt: skip


def _cross_fitted(
    source: str, obs: torch.Tensor, targets: torch.Tensor, steps_at: list[int],
    train: torch.Tensor, config: AnticipationConfig, folds: int = 2,
) -> torch.Tensor:  # fmt: skip
    """``[len(train), T, F]`` decision features of the strokes ``train``, each from a model of
    ``source`` fitted on the other ``folds - 1`` parts of ``train`` only."""
    gen = torch.Generator().manual_seed(config.seed + 1)
    part = torch.empty(len(train), dtype=torch.long)
    part[torch.randperm(len(train), generator=gen)] = torch.arange(len(train)) % folds
    out = None
    for j in range(folds):
        fit_on, held = train[part != j], train[part == j]
        track = track_beliefs(source, obs[fit_on], targets[fit_on], obs[held], targets[held],
                              steps_at, config)  # fmt: skip
        v = track.vectors(config.features)
        if out is None:
            out = v.new_empty(len(train), *v.shape[1:])
        out[part == j] = v
    return out


def run_experiment(
    config: AnticipationConfig | None = None,
    *,
    executor: Executor | None = None,
    cache_dir: str | Path | None = None,
    progress: bool = False,
) -> tuple[ResultTable, ResultTable]:
    """Simulate the trials and their reward table in SAPIEN, then run :func:`run_protocol`.

    The reward table is cached on disk (``cache_dir``, default ``$HGPDM_CACHE`` or
    ``~/.cache/hgpdm_torch``); ``executor`` (an :class:`~hgpdm_torch.parallel.Executor`, e.g.
    a Ray cluster; left open) or else ``config.workers`` local SAPIEN processes fill it; the
    executor also runs the cross-validation's folds (:func:`run_protocol`).
    """
    from ..robots.table_tennis import strokes
    from ..robots.table_tennis.trials import DEFAULT_START_TIMES, make_trials, reward_table

    config = config or AnticipationConfig()
    if tuple(strokes.MOVEMENTS) != MOVEMENTS:
        raise RuntimeError(f"robot movements {strokes.MOVEMENTS} differ from actions {MOVEMENTS}")
    with float64_default():
        trials = make_trials(config.num_trials, seed=config.seed, progress=progress)
        pool = {"workers": config.workers} if executor is None else {"executor": executor}
        rewards = reward_table(
            trials, MOVEMENTS, DEFAULT_START_TIMES, cache_dir=cache_dir, progress=progress, **pool
        )
        return run_protocol(
            trials.obs, trials.obs_times, trials.targets, rewards.to(torch.float64),
            DEFAULT_START_TIMES, config, executor=executor, progress=progress,
        )  # fmt: skip


#: Bar colours by kind of player: the planners (LSPI, MCP) in colour, the same planners on
#: another belief in lighter shades, NAC muted, the baselines and references in greys.
_KINDS = (
    ("LSPI", "tab:orange"),
    ("MCP", "tab:green"),
    ("LSPI on another belief", "#fdc48e"),
    ("MCP on another belief", "#a6dba0"),
    ("NAC", "#b9b3d8"),
    ("baselines", "0.45"),
    ("oracle and after-the-fact references", "0.8"),
)


def _kind(name: str) -> str:
    """Which of :data:`_KINDS` a player of the Fig. 4.6 or demo table is."""
    if name in ("LSPI", "MCP", "NAC"):
        return name
    if name.startswith(("LSPI (", "MCP (")):
        return f"{name.split()[0]} on another belief"
    if name.startswith("oracle") or name.endswith("(after the fact)"):
        return "oracle and after-the-fact references"
    return "baselines"


def player_bars(
    ax: Any, names: list[str], values: list[float], errors: Any, extra: tuple = ()
) -> None:
    """Horizontal bars, one per player from top to bottom in the table's order, each named in
    full on its own line (15 names side by side could not be read), coloured by
    :func:`_kind` so that the planners stand out, with a legend below the axes of the colours
    used and the ``extra`` handles (none covers a bar)."""
    from matplotlib.patches import Patch

    colour = dict(_KINDS)
    kinds = [_kind(n) for n in names]
    ax.barh(range(len(names)), values, xerr=errors, color=[colour[k] for k in kinds],
            capsize=3, error_kw={"lw": 1, "ecolor": "k"})  # fmt: skip
    ax.set_yticks(range(len(names)), names, fontsize=8)
    for label in ax.get_yticklabels():
        if label.get_text() in ("LSPI", "MCP"):
            label.set_fontweight("bold")
    ax.invert_yaxis()  # the table's first row on top
    used = [Patch(color=c, label=k) for k, c in _KINDS if k in kinds]
    ax.figure.legend(handles=[*used, *extra], loc="outside lower center", ncols=3, fontsize=8)


def plot_results(fig6: ResultTable, fig7: ResultTable, out: str | Path) -> list[Path]:
    """Bar charts in the layout of Fig. 4.6 and Fig. 4.7 (PNG files in ``out``): Fig. 4.6 as
    horizontal bars, the planners LSPI and MCP in colour and the references in greys."""
    from matplotlib.figure import Figure  # a bare Figure leaves the pyplot backend alone

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n = fig6.meta.get("valid trials")
    paths = []
    names = fig6.column("method")
    fig = Figure(figsize=(8, 1.6 + 0.3 * len(names)), layout="constrained")
    ax = fig.subplots()
    line = [ax.axvline(n, color="k", lw=0.8, ls="--", label=f"{n} valid trials")] if n else []
    player_bars(ax, names, fig6.column("returns"), fig6.column("SEM"), tuple(line))
    ax.set_xlabel("successful returns (mean and SEM over the repetitions)")
    ax.set_title("Fig. 4.6: anticipatory action selection")
    paths.append(out / _FIGURES[0])
    fig.savefig(paths[-1], dpi=120)
    fig = Figure(figsize=(6.5, 4), layout="constrained")
    ax = fig.subplots()
    episodes = fig7.column("episodes")
    x = torch.arange(len(episodes), dtype=torch.float64)
    colour = dict(_KINDS)
    for shift, name in ((-0.2, "LSPI"), (0.2, "MCP")):
        ax.bar(x + shift, fig7.column(name), 0.4, yerr=fig7.column(f"{name} SEM"), label=name,
               color=colour[name], capsize=3)  # fmt: skip
    ax.set_xticks(x, [str(e) for e in episodes])
    ax.set_xlabel("sampled episodes per training trial")
    ax.set_ylabel("successful returns")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1))  # beside the bars, never over one
    ax.set_title("Fig. 4.7: sample efficiency")
    paths.append(out / _FIGURES[1])
    fig.savefig(paths[-1], dpi=120)
    return paths


def check_reward_cache(parser: argparse.ArgumentParser, cache_dir: Path | None) -> None:
    """End in a usage error naming the path when the reward cache (``--cache-dir``, or the
    default) has a folder where a cache file belongs or a file where a folder belongs
    (:func:`~hgpdm_torch.robots.table_tennis.trials.check_cache_dir`): before any simulation,
    not after it."""
    from ..robots.table_tennis.trials import check_cache_dir

    try:
        check_cache_dir(cache_dir)
    except ValueError as err:
        parser.error(f"argument --cache-dir: {err}" if cache_dir is not None else str(err))


def add_common_arguments(parser: argparse.ArgumentParser, out: str) -> None:
    """The options this command shares with ``hgpdm demo``: how the players decide
    (``--belief``, ``--features``, ``--wait-value``: the :class:`AnticipationConfig` fields of
    the same names), ``--seed``, and where results and rewards go (``--out``, default ``out``;
    ``--cache-dir``)."""
    parser.add_argument(
        "--belief", choices=BELIEFS, default="auto",
        help="the belief source the players decide on: auto (the source with the best "
        "cross-validated return rate on the training folds, among linear-iddm and gp-iddm), "
        "linear-iddm, gp-iddm (the thesis's) or phase-gp-iddm (the phase-aware GP IDDM)",
    )  # fmt: skip
    parser.add_argument(
        "--features", choices=FEATURES, default="moments",
        help="decision features: moments (belief mean, sd and step) or rbf (the thesis's)",
    )  # fmt: skip
    parser.add_argument(
        "--wait-value", choices=WAIT_VALUES, default="lspi",
        help="how MCP values a particle of the next belief: lspi (the best LSPI value there, "
        "waiting included) or stop (its best stopping value, Algorithm 4.2 as printed)",
    )  # fmt: skip
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--out", type=output_folder, default=out)
    parser.add_argument("--cache-dir", type=output_folder, default=None)


def main(argv: list[str]) -> int:
    """CLI entry: ``hgpdm anticipation [--full] [--trials N] [--folds K] [--repetitions R]
    [--belief SOURCE] [--features moments|rbf] [--wait-value lspi|stop]
    [--workers W] [--ray-address ADDRESS] [--seed S] [--out DIR] [--cache-dir DIR]
    [--progress]``."""
    parser = argparse.ArgumentParser(prog="hgpdm anticipation", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--full", action="store_true", help="the thesis's sizes (270 trials, 10x10 CV)"
    )
    parser.add_argument("--trials", type=positive_int, help="simulated strokes before exclusion")
    parser.add_argument("--folds", type=int_at_least(2))
    parser.add_argument("--repetitions", type=positive_int)
    add_executor_arguments(parser, "the rewards' SAPIEN simulations and the folds")
    add_common_arguments(parser, out="hgpdm_anticipation_output")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    check_output_files(parser, "--out", args.out, (*_TABLES, *_FIGURES))
    check_reward_cache(parser, args.cache_dir)
    smoke = smoke_run() or not args.full
    changes = {"seed": args.seed, "workers": args.workers or 1, "belief": args.belief,
               "features": args.features, "wait_value": args.wait_value}  # fmt: skip
    for key, name in (("num_trials", "trials"), ("folds", "folds"), ("repetitions", "repetitions")):
        if getattr(args, name) is not None:
            changes[key] = getattr(args, name)
    try:
        config = AnticipationConfig.smoke(**changes) if smoke else AnticipationConfig(**changes)
    except ValueError as err:  # sizes that contradict each other, e.g. more folds than trials
        parser.error(str(err))
    executor = connect(parser, args.workers, args.ray_address, local=True)
    try:
        fig6, fig7 = run_experiment(
            config, executor=executor, cache_dir=args.cache_dir, progress=args.progress
        )
    finally:
        if executor is not None:
            executor.close()
    print(fig6.to_markdown(".4g"))
    print()
    print(fig7.to_markdown(".4g"))
    out = Path(args.out)
    fig6.to_json(out / _TABLES[0])
    fig7.to_json(out / _TABLES[1])
    for path in plot_results(fig6, fig7, out):
        print(f"saved {path}")
    return 0
