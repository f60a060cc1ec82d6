r"""``hgpdm demo``: the anticipatory table-tennis player, end to end (thesis Ch. 3-4).

1. Simulate opponent strokes and the reward of every movement (forehand, middle, backhand)
   started at every decision time (320 ... 0 ms before the opponent's hit) in the SAPIEN scene
   with the Barrett WAM (:func:`~hgpdm_torch.robots.table_tennis.trials.reward_table`, cached on
   disk). Strokes outside the robot's hitting region (no movement at any time returns them) are
   dropped.
2. Fit the belief sources (:mod:`~hgpdm_torch.decision.sources`: the ``LinearIDDM`` mixture and
   the thesis's GP IDDM) on further opponent strokes that the robot only watched (observations
   and targets, no SAPIEN: watching the opponent is cheap, trying movements is not) and track
   every stroke's belief over the target at every decision time. No model sees a test stroke.
3. Cross-fitting over ``folds`` folds of the simulated strokes, so that every stroke inside the
   hitting region is a test rally exactly once. Per fold, on the other folds only: the belief
   source (``belief="auto"``: the one whose LSPI player returns most training strokes in a
   3-fold cross-validation), LSPI (Algorithm 4.1) on the enumerated training episodes,
   Monte-Carlo planning (Algorithms 4.2-4.3) on LSPI's stopping values with particles from the
   source's own model, and two baselines: the best *blind* strategy (one movement at one start
   time) and the best *fixed-time* strategy (the movement the belief favours, always at one
   start time). Reference rows: LSPI on every candidate source, MCP on the true target as a
   point belief (oracle belief), the oracle that knows the best movement and time of every
   stroke, and the blind strategy picked after the fact on the test rallies.
4. Play the test rallies: at each decision time the player, with MCP, waits or starts a movement;
   the chosen movement is executed in SAPIEN and the ball is returned or missed.
5. Print each player's return rate with an exact 95% interval (Clopper-Pearson) and the paired
   differences MCP / LSPI - each baseline over the same rallies with their 95% intervals
   (Newcombe's square-and-add interval for paired proportions), then save figures: return rates
   with their intervals, one played rally in 3-D and the belief the players used over it.

``hgpdm demo --full`` runs the whole Sec. 4.3 experiment instead (``hgpdm anticipation --full``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..decision.beliefs import decision_indices
from ..decision.mcp import WAIT_VALUES, EarlyStopping
from ..decision.policies import (
    blind_choice,
    fixed_time_choice,
    fixed_time_policy,
    greedy_policy,
    planning_policy,
)
from ..decision.sources import FEATURES, SELECTABLE_SOURCES, BeliefTrack, track_beliefs
from ..parallel import Executor, available_cpus, get_executor, ray_address_type
from ..results import ResultTable
from ..validation import check_choice
from . import anticipation as ant
from .anticipation import BELIEFS, BLIND, FIXED_TIME
from .arguments import (
    check_output_files,
    connect,
    int_at_least,
    positive_int,
)
from .dtype import float64_default
from .intervals import paired_difference_interval, return_rate_interval

__all__ = [
    "BELIEFS",
    "DEFAULT_TRIALS",
    "DEFAULT_WATCHED",
    "DemoResult",
    "Rally",
    "main",
    "plot_demo",
    "run_demo",
    "summary",
]

#: Strokes simulated in SAPIEN by default: about 80% fall inside the hitting region, so that the
#: default run plays about 300 test rallies (a paired 95% interval of about +-0.06).
DEFAULT_TRIALS = 380
#: Further opponent strokes the belief models learn from by default (observed only, never
#: played; watching is cheap, trying movements in SAPIEN is not).
DEFAULT_WATCHED = 600
#: What ``hgpdm demo`` saves into ``--out``: the table, then the figures of :func:`plot_demo`.
_TABLE, _FIGURES = "demo.json", ("return_rates.png", "rally.png")


@dataclass
class Rally:
    """One test stroke played by the MCP player in SAPIEN.

    Attributes:
        trial: index of the stroke among the simulated trials.
        target: the opponent's true target ``x`` on the hitting plane [m].
        action: the movement started; start_time: when, relative to the opponent's hit [s].
        outcome: the :class:`~hgpdm_torch.robots.table_tennis.strokes.StrokeOutcome` of SAPIEN.
    """

    trial: int
    target: float
    action: str
    start_time: float
    outcome: object


@dataclass
class DemoResult:
    """What :func:`run_demo` returns: the table, the played rallies and the beliefs to draw.

    ``rallies`` are the test rallies in stroke order (every stroke inside the hitting region);
    ``target_probs [n_test, T, K]`` is the belief the players decided on (the source chosen for
    the rally's fold) over the target grid ``grid [K]`` at the ``T`` decision times
    ``start_times``; ``beliefs`` maps every source tracked (the candidates and the oracle) to
    its ``[n_test, T, K]`` beliefs; ``sources [n_test]`` names the source of each rally's fold;
    ``successes`` maps each player of the table to its ``[n_test]`` returns on the same rallies
    (the pairs behind the paired differences).
    """

    table: ResultTable
    rallies: list[Rally]
    grid: torch.Tensor
    start_times: tuple[float, ...]
    target_probs: torch.Tensor
    meta: dict = field(default_factory=dict)
    successes: dict[str, torch.Tensor] = field(default_factory=dict)
    beliefs: dict[str, torch.Tensor] = field(default_factory=dict)
    sources: list[str] = field(default_factory=list)


def _play_rally(job: tuple) -> object:
    """One live rally on an executor: ``evaluate(trial, action, start_time)`` under the caller's
    default dtype (a worker process must not fall back to its own)."""
    from ..robots.table_tennis.trials import evaluate

    trial, action, start_time, dtype = job
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        return evaluate(trial, action, start_time)
    finally:
        torch.set_default_dtype(previous)


def _verdict(low: float, high: float, other: str, n: int) -> str:
    """One honest sentence on a paired interval MCP - ``other``."""
    if low > 0:
        return f"MCP returns more balls than the {other} (95% interval above 0, {n} rallies)"
    if high < 0:
        return f"MCP returns fewer balls than the {other} (95% interval below 0, {n} rallies)"
    return (
        f"no significant difference between MCP and the {other} at the 95% level over {n} "
        "rallies (the interval contains 0)"
    )


def _strategy_name(names: list[str]) -> str:
    """One name for a strategy chosen per fold: the name, or ``"per fold: a / b / c"``."""
    return names[0] if len(set(names)) == 1 else "per fold: " + " / ".join(names)


def _check_sizes(num_trials, watched, folds, workers, executor, status, belief, features) -> None:
    for name, value, low in (("num_trials", num_trials, 1), ("watched", watched, 10),
                             ("folds", folds, 2)):  # fmt: skip
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise ValueError(f"workers must be a positive int or None, got {workers!r}")
    if workers is not None and executor is not None:
        raise ValueError("give workers or an executor, not both")
    if status is not None and not callable(status):
        raise TypeError(f"status must be callable or None, got {type(status).__name__}")
    check_choice(belief, "belief", BELIEFS)
    check_choice(features, "features", FEATURES)


def run_demo(
    *,
    num_trials: int = DEFAULT_TRIALS,
    watched: int = DEFAULT_WATCHED,
    folds: int = 3,
    belief: str = "auto",
    features: str = "moments",
    wait_value: str | None = None,
    config: ant.AnticipationConfig | None = None,
    workers: int | None = None,
    executor: Executor | None = None,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    progress: bool = False,
    status: Callable[[str], None] | None = None,
) -> DemoResult:
    """Train the anticipatory player on simulated strokes and play the test rallies in SAPIEN.

    Every simulated stroke inside the robot's hitting region is a test rally once (cross-fitting
    over ``folds`` folds): the belief source, the decision layers (LSPI, MCP) and the baselines
    are chosen and learned on the other folds, the belief models on the ``watched`` strokes.

    Args:
        num_trials: opponent strokes played in SAPIEN (before excluding those outside the
            robot's hitting region).
        watched: further opponent strokes (``>= 10``) the belief models learn from (no robot
            movements).
        folds: cross-fitting folds (``>= 2``); each learns from ``(folds - 1) / folds`` of the
            strokes.
        belief: the belief source the players decide on: ``"auto"`` (default: per fold, the
            source of :data:`~hgpdm_torch.decision.sources.SELECTABLE_SOURCES` whose LSPI
            player returns most training strokes in a 3-fold cross-validation), or one of them
            (``"linear-iddm"``, ``"gp-iddm"``, the thesis's).
        features: the decision features (:data:`~hgpdm_torch.decision.sources.FEATURES`):
            ``"moments"`` (default) or the thesis's ``"rbf"``.
        wait_value: how MCP values a particle of the next belief
            (:data:`~hgpdm_torch.decision.mcp.WAIT_VALUES`): ``"lspi"`` (the best LSPI value
            there, waiting included where the next step may wait) or the thesis's ``"stop"``
            (its best stopping value); ``None``: ``config.wait_value`` (``"lspi"`` by default).
        config: GP IDDM, basis, LSPI and MCP settings (default: the full experiment's with 20
            RBF centres and the GP IDDM on 150 of the watched strokes).
        workers: SAPIEN processes for the reward table and the live rallies (default: all
            cores, at most 4).
        executor: an :class:`~hgpdm_torch.parallel.Executor` (e.g. a Ray cluster) to simulate
            on instead of ``workers`` local processes; left open.
        seed: seeds the strokes, the folds and the planner.
        cache_dir: reward-table cache (default ``$HGPDM_CACHE`` or ``~/.cache/hgpdm_torch``).
        progress: tqdm bars.
        status: called with one short line at the end of each stage (simulate, fit, learn,
            play) giving its elapsed seconds; ``None`` for silence.

    Returns:
        A :class:`DemoResult`; its table has each player's returns, rate and exact 95%
        interval, and its meta the paired differences of MCP and LSPI against the best blind and
        the best fixed-time strategy chosen on the training folds, with their 95% intervals
        (:func:`paired_difference_interval`).

    Raises:
        ValueError: bad sizes (``num_trials``, ``watched``, ``workers``, ``folds``), an unknown
            ``belief`` or ``features``, ``workers`` with an ``executor``, or too few strokes
            inside the hitting region for the folds.
    """
    from ..robots.table_tennis import strokes
    from ..robots.table_tennis.trials import DEFAULT_START_TIMES

    _check_sizes(num_trials, watched, folds, workers, executor, status, belief, features)
    config = config or ant.AnticipationConfig(centres=20, iddm_trials=150, seed=seed)
    wait_value = check_choice(
        config.wait_value if wait_value is None else wait_value, "wait_value", WAIT_VALUES
    )
    movements = tuple(strokes.MOVEMENTS)
    if movements != ant.MOVEMENTS:
        raise RuntimeError(f"robot movements {movements} differ from actions {ant.MOVEMENTS}")
    start_times = DEFAULT_START_TIMES
    say = status or (lambda line: None)
    pool = (
        executor
        if executor is not None
        else get_executor(workers or max(1, min(4, available_cpus())))
    )
    candidates = SELECTABLE_SOURCES if belief == "auto" else (belief,)
    try:
        with float64_default():
            trials, rewards, valid, t_sim = _simulate(
                num_trials, folds, movements, start_times, pool, seed, cache_dir, progress, say
            )
            n = len(valid)
            gen = torch.Generator().manual_seed(seed)
            fold_of = torch.empty(n, dtype=torch.long)
            fold_of[torch.randperm(n, generator=gen)] = torch.arange(n) % folds
            tracks, t_fit = _track(
                trials, watched, candidates, start_times, config, seed, progress, say
            )
            play = _learn_and_decide(
                tracks, rewards, valid, fold_of, candidates, features, wait_value, config,
                gen, progress=progress,
            )  # fmt: skip
            say(
                f"learn: belief choice, baselines, LSPI and MCP decisions on {folds} folds "
                f"({play.seconds:.0f} s)"
            )
            rallies, t_play = _play_live(
                trials, valid, play, movements, start_times, pool, progress, say
            )
    finally:
        if executor is None:
            pool.close()
    won = play.won
    won["MCP"] = torch.tensor([bool(r.outcome.success) for r in rallies])
    settings = {
        "num_trials": num_trials,
        "watched": watched,
        "valid": n,
        "folds": folds,
        "seed": seed,
        "belief": belief,
        "features": features,
        "wait_value": wait_value,
    }
    timings = {"simulate [s]": t_sim, "fit [s]": t_fit, "learn [s]": play.seconds,
               "MCP per decision [ms]": 1e3 * play.plan_seconds / max(1, play.decisions),
               "play [s]": t_play}  # fmt: skip
    table, meta = _report(won, play, tracks, trials, valid, settings, timings)
    used = torch.stack([tracks[s].prob[int(i)] for s, i in zip(play.sources_per_rally, valid,
                                                                strict=True)])  # fmt: skip
    beliefs = {src: track.prob[valid] for src, track in tracks.items()}
    return DemoResult(table, rallies, tracks["oracle"].grid, start_times, used, meta, won,
                      beliefs, play.sources_per_rally)  # fmt: skip


def _simulate(
    num_trials, folds, movements, start_times, pool, seed, cache_dir, progress, say
) -> tuple[Any, torch.Tensor, torch.Tensor, float]:
    """The opponent's strokes, every (movement, start time) of the robot on each in SAPIEN (the
    reward table), and the strokes inside the hitting region (``valid``)."""
    from ..robots.table_tennis.trials import make_trials, reward_table

    clock = time.perf_counter()
    trials = make_trials(num_trials, seed=seed, progress=progress)
    rewards = reward_table(
        trials, movements, start_times, executor=pool, cache_dir=cache_dir, progress=progress,
    ).to(torch.float64)  # fmt: skip
    t_sim = time.perf_counter() - clock
    valid = torch.nonzero(ant.valid_trials(rewards)).flatten()
    n = len(valid)
    say(
        f"simulate: {num_trials} strokes x {rewards[0].numel()} (movement, start) in "
        f"SAPIEN, {n} inside the hitting region ({t_sim:.0f} s)"
    )
    if n < folds or n - math.ceil(n / folds) < 6:
        raise ValueError(
            f"only {n} of {num_trials} strokes are inside the hitting region; "
            f"{folds} folds need more: simulate more (num_trials)"
        )
    return trials, rewards, valid, t_sim


def _track(
    trials, watched, candidates, start_times, config, seed, progress, say
) -> tuple[dict[str, Any], float]:
    """Each candidate belief source (and the oracle) fitted on ``watched`` further strokes and
    tracked over the trials' observations up to the last decision."""
    from ..robots.table_tennis.trials import make_trials

    clock = time.perf_counter()
    seen = make_trials(watched, seed=seed + 1, progress=progress)
    if not torch.equal(seen.obs_times, trials.obs_times):
        raise RuntimeError("watched strokes must share the trials' observation times")
    steps_at = decision_indices(trials.obs_times, start_times)
    last = max(steps_at) + 1
    # clip: a simulated return may land a little beyond the grid (the hitting region); the
    # oracle's reference belief then sits on the grid's edge, as the models' beliefs can
    tracks = {
        src: track_beliefs(src, seen.obs[:, :last], seen.targets, trials.obs[:, :last],
                           trials.targets, steps_at, config, clip=True)
        for src in (*candidates, "oracle")
    }  # fmt: skip
    t_fit = time.perf_counter() - clock
    say(f"fit: {', '.join(candidates)} on {watched} watched strokes, beliefs tracked "
        f"({t_fit:.0f} s)")  # fmt: skip
    return tracks, t_fit


def _play_live(
    trials, valid, play, movements, start_times, pool, progress, say
) -> tuple[list[Rally], float]:
    """Every MCP decision executed in SAPIEN: one rally per valid stroke."""
    from ..progress import tqdm

    clock = time.perf_counter()
    dtype = torch.get_default_dtype()
    jobs = [
        (trials[int(i)], movements[int(play.stop_action[j]) - 1],
         start_times[int(play.stop_step[j])], dtype)
        for j, i in enumerate(valid.tolist())
    ]  # fmt: skip
    outcomes = list(
        tqdm(pool.map(_play_rally, jobs), total=len(jobs), disable=not progress,
             desc="play (SAPIEN)", leave=False)
    )  # fmt: skip
    rallies = [
        Rally(int(i), float(trials.targets[i]), job[1], job[2], outcome)
        for i, job, outcome in zip(valid.tolist(), jobs, outcomes, strict=True)
    ]
    t_play = time.perf_counter() - clock
    say(f"play: {len(jobs)} rallies of the MCP player in SAPIEN ({t_play:.0f} s)")
    return rallies, t_play


def _report(
    won: dict[str, torch.Tensor], play: _Play, tracks: dict[str, Any], trials: Any,
    valid: torch.Tensor, settings: dict[str, Any], timings: dict[str, float],
) -> tuple[ResultTable, dict[str, Any]]:  # fmt: skip
    """The result table (each player's returns, rate and 95% interval) and its meta: the belief
    and baselines chosen, the paired differences of MCP and LSPI against the baselines with
    their intervals, the verdict, the timings, the agreement of the live rallies with the
    reward table, the belief fits and each belief's mean error at the decision times."""
    n, folds, num_trials = settings["valid"], settings["folds"], settings["num_trials"]
    # the scene is deterministic: each live rally must reproduce the reward the stopping
    # problem gave the planner's (step, action) decision
    agree = int((won["MCP"] == (play.table_reward > 0)).sum())
    table = ResultTable(
        f"hgpdm demo: anticipatory table tennis, {n} test rallies ({folds}-fold cross-fitting "
        f"over {n} of {num_trials} strokes)",
        ["player", "returns", "rate", "95% low", "95% high", "played in"],
        meta=dict(settings),
    )
    for p in won:
        k = int(won[p].sum())
        low, high = return_rate_interval(k, n)
        where = "SAPIEN" if p == "MCP" else "reward table (SAPIEN)"
        table.add(**{"player": p, "returns": k, "rate": k / n, "95% low": low, "95% high": high,
                     "played in": where})  # fmt: skip
    meta = {
        "belief used": _strategy_name(play.sources),
        "belief CV return rates": play.cv_rates,
        BLIND: _strategy_name(play.blind),
        FIXED_TIME: _strategy_name(play.fixed_time),
    }
    for player in ("MCP", "LSPI"):
        for other in (BLIND, FIXED_TIME):
            diff, low, high = paired_difference_interval(won[player], won[other])
            meta[f"{player} - {other}"] = diff
            meta[f"{player} - {other} 95% low"] = low
            meta[f"{player} - {other} 95% high"] = high
    meta["MCP / best blind (training folds)"] = int(won["MCP"].sum()) / max(
        1, int(won[BLIND].sum())
    )
    meta["verdict"] = "; ".join(
        _verdict(meta[f"MCP - {o} 95% low"], meta[f"MCP - {o} 95% high"], o, n)
        for o in (BLIND, FIXED_TIME)
    )
    meta.update(timings)
    meta["live = table"] = f"{agree}/{n}"
    meta["belief fits"] = {src: track.fits for src, track in tracks.items() if track.fits}
    # how far each belief's mean lies from the true target at each decision time
    truth = trials.targets[valid]
    for src, track in tracks.items():
        err = 100 * (track.mean()[valid] - truth[:, None]).abs().mean(0)
        meta[f"belief mean MAE [cm], {src}"] = [round(float(e), 1) for e in err]
    table.meta.update(meta)
    return table, meta


@dataclass
class _Play:
    """The learning stage's decisions on every rally (positions among the valid strokes)."""

    won: dict[str, torch.Tensor]
    stop_step: torch.Tensor
    stop_action: torch.Tensor
    table_reward: torch.Tensor
    sources: list[str]
    sources_per_rally: list[str]
    cv_rates: list[dict[str, float]]
    blind: list[str]
    fixed_time: list[str]
    seconds: float
    plan_seconds: float
    decisions: int


def _learn_and_decide(
    tracks: dict[str, BeliefTrack], rewards: torch.Tensor, valid: torch.Tensor,
    fold_of: torch.Tensor, candidates: tuple[str, ...], features: str, wait_value: str,
    config: ant.AnticipationConfig, gen: torch.Generator, *, progress: bool = False,
) -> _Play:  # fmt: skip
    """Per fold: the belief source (by CV on the training folds when there are candidates), the
    baselines chosen on the training folds, LSPI and the MCP decisions on the test rallies,
    and the oracle-belief MCP player; the reward table scores all but MCP's live play."""
    from ..progress import tqdm
    from ..robots.table_tennis.trials import DEFAULT_START_TIMES

    n, folds = len(valid), int(fold_of.max()) + 1
    num_steps = rewards.shape[-1]
    movements = ant.MOVEMENTS
    rule = EarlyStopping(config.particles, config.confidence, min(100, config.particles))
    players = [BLIND, FIXED_TIME, "LSPI", "MCP", *(f"LSPI ({s} belief)" for s in candidates),
               "MCP (oracle belief)", "oracle (best movement and time per stroke)",
               "best blind (after the fact)"]  # fmt: skip
    won = {p: torch.zeros(n, dtype=torch.bool) for p in players}
    stop_step = torch.zeros(n, dtype=torch.long)
    stop_action = torch.zeros(n, dtype=torch.long)
    table_reward = torch.zeros(n)
    sources, per_rally, rates, blind, fixed = [], [""] * n, [], [], []
    clock, t_plan, decisions = time.perf_counter(), 0.0, 0
    reward = rewards[valid]
    vectors = {src: track.vectors(features)[valid] for src, track in tracks.items()}
    start_times = DEFAULT_START_TIMES
    for k in tqdm(range(folds), disable=not progress, desc="learn + plan (folds)", leave=False):
        at = torch.nonzero(fold_of == k).flatten()  # positions among the valid strokes
        tr = torch.nonzero(fold_of != k).flatten()
        source, cv, learned = ant.learn_players(vectors, reward, tr, at, candidates, features,
                                                config)  # fmt: skip
        sources.append(source)
        rates.append(cv)
        for j in at.tolist():
            per_rally[j] = source
        a, t = blind_choice(reward[tr])
        blind.append(f"always {movements[a]} @{round(-1000 * start_times[t])}ms")
        won[BLIND][at] = reward[at, a, t] > 0
        for src in (*candidates, "oracle"):
            train, test, basis, q = learned[src]
            if src in candidates:
                won[f"LSPI ({src} belief)"][at] = test.run(greedy_policy(q, basis, test)).reward > 0
            if src == source:
                won["LSPI"][at] = test.run(greedy_policy(q, basis, test)).reward > 0
                step, q_t = fixed_time_choice(train, basis, config.ridge)
                fixed.append(f"belief's movement @{round(-1000 * start_times[step])}ms")
                won[FIXED_TIME][at] = test.run(fixed_time_policy(q_t, basis, step)).reward > 0
            if src in (source, "oracle"):
                c = time.perf_counter()
                policy = planning_policy(tracks[src], valid[at], q, basis, rule, num_steps,
                                         features, gen, wait_value)  # fmt: skip
                decided = test.run(policy)
                t_plan += time.perf_counter() - c
                if src == "oracle":
                    won["MCP (oracle belief)"][at] = decided.reward > 0
                else:
                    decisions += int((decided.stop_step + 1).sum())
                    stop_step[at], stop_action[at] = decided.stop_step, decided.stop_action
                    table_reward[at] = decided.reward.to(table_reward.dtype)
    won["oracle (best movement and time per stroke)"][:] = (reward > 0).flatten(1).any(1)
    a, t = blind_choice(reward)  # on all the rallies: after the fact
    won["best blind (after the fact)"] = reward[:, a, t] > 0
    # won["MCP"] is the reward table's; the caller replaces it by the live SAPIEN rallies
    return _Play(won, stop_step, stop_action, table_reward, sources, per_rally, rates, blind,
                 fixed, time.perf_counter() - clock, t_plan, decisions)  # fmt: skip


def plot_demo(result: DemoResult, out: str | Path) -> list[Path]:
    """Save the return rates with their 95% intervals (horizontal bars, the planners LSPI and
    MCP in colour, the references in greys), one played rally in 3-D and its belief over the
    target (PNGs)."""
    from matplotlib.figure import Figure  # a bare Figure leaves the pyplot backend alone

    from ..robots.table_tennis.draw import MOVEMENT_COLORS, draw_stroke, draw_table
    from ..robots.wam import WAM

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    table = result.table
    names, rates = table.column("player"), table.column("rate")
    lows, highs = table.column("95% low"), table.column("95% high")
    errors = [[r - lo for r, lo in zip(rates, lows, strict=True)],
              [hi - r for r, hi in zip(rates, highs, strict=True)]]  # fmt: skip
    fig = Figure(figsize=(9, 2.4 + 0.32 * len(names)), layout="constrained")
    ax = fig.subplots()
    ant.player_bars(ax, names, rates, errors)
    ax.set_xlabel("return rate on the test rallies (exact 95% interval)")
    ax.set_xlim(0, 1.05)
    m = result.meta
    title = table.title
    for other in (BLIND, FIXED_TIME):
        if f"MCP - {other}" in m:
            title += (
                f"\nMCP - {other}, paired: {m[f'MCP - {other}']:+.3f} "
                f"[{m[f'MCP - {other} 95% low']:+.3f}, {m[f'MCP - {other} 95% high']:+.3f}]"
            )
    # over the whole figure, not the axes (shifted right by the long names), and wrapped
    fig.suptitle("\n".join(textwrap.fill(line, 110) for line in title.split("\n")), fontsize=9)
    paths.append(out / _FIGURES[0])
    fig.savefig(paths[-1], dpi=120)

    # the first returned rally (else the first one) and the belief that led to it
    j = next((k for k, r in enumerate(result.rallies) if r.outcome.success), 0)
    rally = result.rallies[j]
    used = result.sources[j] if result.sources else "the players'"
    beliefs = [(f"belief used by the players ({used})", result.target_probs)]
    beliefs += [(f"belief ({src}, not used)", probs) for src, probs in result.beliefs.items()
                if src not in (used, "oracle")]  # fmt: skip
    columns = 1 + len(beliefs)
    fig = Figure(figsize=(5.5 * columns, 4.2))
    ax3 = fig.add_subplot(1, columns, 1, projection="3d")
    draw_table(ax3)
    draw_stroke(ax3, rally.outcome, WAM(), color=MOVEMENT_COLORS[rally.action], label=rally.action)
    ax3.set_title(
        f"stroke {rally.trial}: {rally.action} started {round(-1000 * rally.start_time)} ms "
        f"before the hit -> {'returned' if rally.outcome.success else 'missed'}",
        fontsize=9,
    )
    for k, (label, probs) in enumerate(beliefs):
        ax = fig.add_subplot(1, columns, 2 + k)
        for t, s in enumerate(result.start_times):
            ax.plot(result.grid, probs[j, t], label=f"{round(-1000 * s)} ms before the hit")
        ax.axvline(rally.target, color="k", ls="--", lw=1, label="true target")
        ax.set(xlabel="target x on the hitting plane [m]", ylabel=label)
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / _FIGURES[1])
    fig.savefig(paths[-1], dpi=120)
    return paths


def summary(result: DemoResult) -> str:
    """The paired comparisons of MCP and LSPI with the baselines chosen on the training folds,
    as printed under the table."""
    m = result.meta
    lines = [f"belief: {m['belief used']}; {BLIND}: {m[BLIND]}; {FIXED_TIME}: {m[FIXED_TIME]}"]
    for player in ("MCP", "LSPI"):
        for other in (BLIND, FIXED_TIME):
            key = f"{player} - {other}"
            lines.append(
                f"{key}, paired over the same rallies: {m[key]:+.3f}, 95% interval "
                f"[{m[key + ' 95% low']:+.3f}, {m[key + ' 95% high']:+.3f}]"
            )
    lines.append(f"(Newcombe square-and-add intervals) {m['verdict']}.")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    """CLI entry: ``hgpdm demo [--trials N] [--watched M] [--folds K] [--belief SOURCE]
    [--features moments|rbf] [--wait-value lspi|stop] [--workers W]
    [--ray-address ADDRESS] [--seed S] [--out DIR] [--cache-dir DIR] [--full]
    [--progress | --quiet]``.

    Progress: tqdm bars when stderr is a terminal (or with ``--progress``); a one-line status
    per stage on stderr unless ``--quiet``, which leaves only the results on stdout.
    """
    parser = argparse.ArgumentParser(prog="hgpdm demo", description=__doc__.split("\n")[0])
    parser.add_argument(
        "--trials", type=positive_int, default=None,
        help=f"strokes played in SAPIEN ({DEFAULT_TRIALS})",
    )  # fmt: skip
    parser.add_argument(
        "--watched",
        type=int_at_least(10),
        default=None,
        help=f"further strokes the belief models learn from ({DEFAULT_WATCHED})",
    )
    parser.add_argument(
        "--folds", type=int_at_least(2), default=3,
        help="cross-fitting folds: every stroke in the hitting region is a test rally once (3)",
    )  # fmt: skip
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="SAPIEN processes (all cores, at most 4); with --ray-address as in anticipation",
    )
    parser.add_argument(
        "--ray-address",
        type=ray_address_type,
        default=None,
        help="simulate the reward table on Ray: 'local', 'auto' or HOST:PORT of a head node",
    )
    ant.add_common_arguments(parser, out="hgpdm_demo_output")
    parser.add_argument(
        "--full", action="store_true", help="run the full Sec. 4.3 experiment instead"
    )
    noise = parser.add_mutually_exclusive_group()
    noise.add_argument(
        "--progress", action="store_true",
        help="tqdm bars even when stderr is not a terminal (default: only on a terminal)",
    )  # fmt: skip
    noise.add_argument(
        "--quiet", action="store_true", help="no bars and no status lines: only the results"
    )
    args = parser.parse_args(argv)
    if args.full and (args.trials is not None or args.watched is not None):
        parser.error("--trials and --watched set the demo's sizes; --full uses the thesis's")
    if not args.full:  # --full: anticipation's parser checks its own outputs
        check_output_files(parser, "--out", args.out, (_TABLE, *_FIGURES))
    ant.check_reward_cache(parser, args.cache_dir)
    bars = not args.quiet and (args.progress or sys.stderr.isatty())
    if args.full:
        extra = [
            "--out",
            str(args.out),
            "--seed",
            str(args.seed),
            "--belief",
            args.belief,
            "--features",
            args.features,
            "--wait-value",
            args.wait_value,
        ]
        if args.ray_address is None:
            extra += ["--workers", str(args.workers or max(1, os.cpu_count() or 1))]
        else:
            extra += ["--ray-address", args.ray_address]
            extra += ["--workers", str(args.workers)] if args.workers else []
        extra += ["--progress"] if bars else []
        extra += ["--cache-dir", str(args.cache_dir)] if args.cache_dir else []
        return ant.main(["--full", *extra])
    start = time.perf_counter()

    def status(line: str) -> None:
        print(f"[hgpdm demo {time.perf_counter() - start:5.0f} s] {line}", file=sys.stderr,
              flush=True)  # fmt: skip

    executor = connect(parser, args.workers, args.ray_address)
    try:
        result = run_demo(
            num_trials=DEFAULT_TRIALS if args.trials is None else args.trials,
            watched=DEFAULT_WATCHED if args.watched is None else args.watched,
            folds=args.folds, belief=args.belief, features=args.features,
            wait_value=args.wait_value,
            workers=None if executor is not None else args.workers, executor=executor,
            seed=args.seed, cache_dir=args.cache_dir, progress=bars,
            status=None if args.quiet else status,
        )  # fmt: skip
    finally:
        if executor is not None:
            executor.close()
    print(result.table.to_markdown(".3g"))
    print()
    print(summary(result))
    print()
    skip = {"verdict", "belief used", BLIND, FIXED_TIME}
    skip |= {k for k in result.meta if k.startswith(("MCP - ", "LSPI - "))}
    print(", ".join(f"{k}: {v:.3g}" if isinstance(v, float) else f"{k}: {v}"
                    for k, v in result.meta.items() if k not in skip))  # fmt: skip
    out = Path(args.out)
    result.table.to_json(out / _TABLE)
    for path in plot_demo(result, out):
        print(f"saved {path}")
    if not args.quiet:
        status(f"done ({time.perf_counter() - start:.0f} s in all)")
    return 0
