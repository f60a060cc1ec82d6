r"""``hgpdm demo``: the anticipatory table-tennis player, end to end (thesis Ch. 3-4).

1. Simulate opponent strokes and the reward of every movement (forehand, middle, backhand)
   started at every decision time (320 ... 0 ms before the opponent's hit) in the SAPIEN scene
   with the Barrett WAM (:func:`~hgpdm_torch.robots.table_tennis.trials.reward_table`, cached on
   disk). Strokes outside the robot's hitting region (no movement at any time returns them) are
   dropped.
2. Fit the IDDM (continuous target, Ch. 3) on further opponent strokes that the robot only
   watched (observations and targets, no SAPIEN: watching the opponent is cheap, trying
   movements is not); the online filter (Algorithm 3.2) gives every stroke's belief (latent
   state and target histogram) at every decision time. The IDDM never sees a test stroke.
3. Cross-fitting over ``folds`` folds of the simulated strokes, so that every stroke inside the
   hitting region is a test rally exactly once: per fold, learn when and how to hit (Ch. 4) on
   the other folds -- LSPI (Algorithm 4.1) on the enumerated training episodes and Monte-Carlo
   planning (Algorithms 4.2-4.3) on top of LSPI's stopping values -- and the fixed-strategy
   baselines (each single movement started 240 ms before the hit; the best movement chosen at
   a fixed time).
4. Play the test rallies: at each decision time the player, with MCP, waits or starts a movement;
   the chosen movement is executed in SAPIEN and the ball is returned or missed.
5. Print each player's return rate with an exact 95% interval (Clopper-Pearson) and the paired
   difference MCP - best fixed strategy over the same rallies with its 95% interval (Newcombe's
   square-and-add interval for paired proportions), then save figures: return rates with their
   intervals, one played rally in 3-D and the belief over the target during that stroke.

``hgpdm demo --full`` runs the whole Sec. 4.3 experiment instead (``hgpdm anticipation --full``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..decision.basis import RadialBasis
from ..decision.beliefs import decision_indices, fit_beliefs
from ..decision.lspi import lspi
from ..decision.mcp import MonteCarloPlanner
from ..decision.policies import fixed_time_policy, greedy_policy, mcp_policy, stop_only_q
from ..decision.stopping import StoppingProblem
from ..inference import BeliefMixture
from ..models import LinearIDDM
from ..parallel import Executor, available_cpus, get_executor, ray_address_type
from . import anticipation as ant
from .arguments import (
    int_at_least,
    non_negative_int,
    output_folder,
    positive_int,
    random_seed,
)
from .dtype import float64_default
from .intervals import paired_difference_interval, return_rate_interval
from .table import ResultTable

__all__ = [
    "DEFAULT_TRIALS",
    "DEFAULT_WATCHED",
    "DemoResult",
    "Rally",
    "main",
    "plot_demo",
    "run_demo",
    "summary",
]

#: Strokes simulated in SAPIEN by default: about 85% fall inside the hitting region, so that the
#: default run (seed 0) plays more than 60 test rallies.
DEFAULT_TRIALS = 80
#: Further opponent strokes the IDDM is fitted on by default (observed only, never played).
DEFAULT_WATCHED = 150
#: Fixed strategies: the players whose timing does not depend on the belief.
FIXED_PREFIXES = ("always ", "best movement @")


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
    ``target_probs [n_test, T, K]`` is the belief over the target grid ``grid [K]`` of each of
    them at the ``T`` decision times ``start_times``; ``successes`` maps each player of the
    table to its ``[n_test]`` returns on the same rallies (the pairs behind the paired
    difference). ``linear_probs [n_test, T, K]`` is the belief README recommends for target
    prediction, the :class:`~hgpdm_torch.inference.BeliefMixture` of two
    :class:`~hgpdm_torch.models.LinearIDDM` (without and with the rank-1 intention-state
    interaction, everything chosen by cross-validation) fitted on the IDDM's training strokes
    (all of them, also where the IDDM takes a subset), for comparison only: the players decide
    on the IDDM's belief.
    """

    table: ResultTable
    rallies: list[Rally]
    grid: torch.Tensor
    start_times: tuple[float, ...]
    target_probs: torch.Tensor
    meta: dict = field(default_factory=dict)
    successes: dict[str, torch.Tensor] = field(default_factory=dict)
    linear_probs: torch.Tensor | None = None


def _linear_beliefs(
    obs: torch.Tensor, targets: torch.Tensor, train: torch.Tensor, test: torch.Tensor,
    steps_at: list[int], grid: torch.Tensor,
) -> torch.Tensor:  # fmt: skip
    """``[len(test), T, K]`` beliefs, at the decision steps, of the equal mixture of two
    :class:`LinearIDDM` (without and with the rank-1 interaction; noise kind, prior, T and eps
    by cross-validation) fitted on the ``train`` strokes."""
    models = []
    for rank in (0, 1):
        model = LinearIDDM(interaction_rank=rank, select="cv", temperature="cv", forgetting="cv")
        with warnings.catch_warnings():  # a comparison only: a prior scale at its grid's edge
            warnings.simplefilter("ignore")  # (the held-out likelihood is flat in it) is fine
            models.append(model.fit(obs[train], targets[train]))
    belief = BeliefMixture(models).beliefs(obs[test][:, : max(steps_at) + 1], grid)
    return belief.prob[:, steps_at]


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


def _verdict(low: float, high: float, best: str, n: int) -> str:
    """One honest sentence on the paired interval MCP - best fixed strategy."""
    if low > 0:
        return f"MCP returns more balls than {best} (the 95% interval is above 0, {n} rallies)"
    if high < 0:
        return f"MCP returns fewer balls than {best} (the 95% interval is below 0, {n} rallies)"
    return (
        f"no significant difference between MCP and {best} at the 95% level over {n} rallies "
        "(the interval contains 0)"
    )


def run_demo(
    *,
    num_trials: int = DEFAULT_TRIALS,
    watched: int = DEFAULT_WATCHED,
    folds: int = 3,
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
    over ``folds`` folds): the decision layers (LSPI, MCP and the fixed-time baselines) are
    learned on the other folds, the IDDM on the ``watched`` strokes only.

    Args:
        num_trials: opponent strokes played in SAPIEN (before excluding those outside the
            robot's hitting region).
        watched: further opponent strokes the IDDM is trained on (no robot movements). With
            ``0`` the IDDM of each fold is fitted on that fold's training strokes instead.
        folds: cross-fitting folds (``>= 2``); each learns from ``(folds - 1) / folds`` of the
            strokes.
        config: IDDM, basis, LSPI and MCP settings (default: the full experiment's with 20
            RBF centres; learning takes seconds, the SAPIEN simulation minutes).
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
        interval, and its meta the paired difference MCP - best fixed strategy with its 95%
        interval (:func:`paired_difference_interval`).

    Raises:
        ValueError: bad sizes (``num_trials``, ``watched``, ``workers``, ``folds``), ``workers``
            with an ``executor``, or too few strokes inside the hitting region for the folds.
    """
    from tqdm.auto import tqdm

    from ..robots.table_tennis import strokes
    from ..robots.table_tennis.trials import DEFAULT_START_TIMES, make_trials, reward_table

    for name, value, low in (
        ("num_trials", num_trials, 1),
        ("watched", watched, 0),
        ("folds", folds, 2),
    ):
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
    config = config or ant.AnticipationConfig(centres=20, iddm_trials=10_000, seed=seed)
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
    try:
        with float64_default():
            clock = time.perf_counter()
            trials = make_trials(num_trials, seed=seed, progress=progress)
            rewards = reward_table(
                trials, movements, start_times, executor=pool, cache_dir=cache_dir,
                progress=progress,
            ).to(torch.float64)  # fmt: skip
            t_sim = time.perf_counter() - clock
            valid = torch.nonzero(ant.valid_trials(rewards)).flatten()
            n = len(valid)
            say(
                f"simulate: {num_trials} strokes x {rewards[0].numel()} (movement, start) in "
                f"SAPIEN, {n} inside the hitting region ({t_sim:.0f} s)"
            )
            if n < folds or n - math.ceil(n / folds) < 4:
                raise ValueError(
                    f"only {n} of {num_trials} strokes are inside the hitting region; "
                    f"{folds} folds need more: simulate more (num_trials)"
                )
            gen = torch.Generator().manual_seed(seed)
            fold_of = torch.empty(n, dtype=torch.long)
            fold_of[torch.randperm(n, generator=gen)] = torch.arange(n) % folds

            clock = time.perf_counter()
            obs, targets = trials.obs, trials.targets
            steps_at = decision_indices(trials.obs_times, start_times)
            shared = None
            if watched:
                seen = make_trials(watched, seed=seed + 1, progress=progress)
                if not torch.equal(seen.obs_times, trials.obs_times):
                    raise RuntimeError("watched strokes must share the trials' observation times")
                obs, targets = torch.cat([obs, seen.obs]), torch.cat([targets, seen.targets])
                iddm_train = num_trials + torch.arange(watched)
                shared = fit_beliefs(obs, targets, steps_at, iddm_train, valid, config)
            t_fit = time.perf_counter() - clock
            fits = []  # FitResult summaries of the IDDM(s), for the result
            if shared is not None:
                fits.append(shared.model.fit_result.summary())
                say(f"fit: IDDM on {watched} watched strokes ({_fit_words(fits)}), beliefs "
                    f"filtered ({t_fit:.0f} s)")  # fmt: skip

            # per fold: the baselines and LSPI are scored on the reward table, MCP decides
            players = [f"always {m} @240ms" for m in movements]
            players += [f"best movement @{round(-1000 * s)}ms" for s in ant.ORACLE_TIMES]
            players += ["LSPI", "MCP"]
            won = {p: torch.zeros(n, dtype=torch.bool) for p in players}
            stop_step = torch.zeros(n, dtype=torch.long)
            stop_action = torch.zeros(n, dtype=torch.long)
            table_reward = torch.zeros(n)
            probs = torch.zeros(n, len(start_times), config.grid_size)
            linear_probs = torch.zeros_like(probs)
            grid = torch.linspace(-config.grid_max, config.grid_max, config.grid_size)
            single = start_times.index(ant.SINGLE_TIME)
            t_learn = t_plan = 0.0
            decisions = 0
            bar = tqdm(total=folds, disable=not progress, desc="learn + plan (folds)", leave=False)
            for k in range(folds):
                at = torch.nonzero(fold_of == k).flatten()  # positions among the valid strokes
                train, test = valid[fold_of != k], valid[at]
                clock = time.perf_counter()
                beliefs = shared
                if beliefs is None:  # no watched strokes: this fold's IDDM on its training set
                    beliefs = fit_beliefs(obs, targets, steps_at, train, valid, config)
                    fits.append(beliefs.model.fit_result.summary())
                    t_fit += time.perf_counter() - clock
                    clock = time.perf_counter()
                vectors = beliefs.vectors()[:num_trials]
                problem = StoppingProblem(vectors, rewards)
                train_p, test_p = problem.subset(train), problem.subset(test)
                basis = RadialBasis(config.centres, seed=seed, bias=True).fit(
                    train_p.beliefs.reshape(-1, vectors.shape[-1])
                )
                for a, name in enumerate(movements):
                    won[f"always {name} @240ms"][at] = test_p.rewards[:, a, single] > 0
                for s in ant.ORACLE_TIMES:
                    step = start_times.index(s)
                    q_t = stop_only_q(train_p, step, basis, config.ridge)
                    episodes = test_p.run(fixed_time_policy(q_t, basis, step))
                    won[f"best movement @{round(-1000 * s)}ms"][at] = episodes.reward > 0
                enumerated = train_p.transitions(train_p.enumerate_episodes(), unique=True)
                q = lspi(enumerated, features=basis, ridge=config.ridge).q
                won["LSPI"][at] = test_p.run(greedy_policy(q, basis, test_p)).reward > 0
                planner = MonteCarloPlanner(
                    beliefs.model, beliefs.belief_filter, q, basis,
                    num_particles=config.particles, confidence=config.confidence,
                )  # fmt: skip
                t_learn += time.perf_counter() - clock
                clock = time.perf_counter()
                # the MCP player's decisions on this fold's rallies (positions in `valid` of
                # the fold's trials index the beliefs)
                decided = test_p.run(mcp_policy(planner, beliefs, test, test_p.horizon, gen))
                t_plan += time.perf_counter() - clock
                decisions += int((decided.stop_step + 1).sum())
                stop_step[at], stop_action[at] = decided.stop_step, decided.stop_action
                table_reward[at] = decided.reward.to(table_reward.dtype)
                probs[at] = beliefs.log_prob[test].exp().to(probs.dtype)
                seen_by = iddm_train if watched else train  # the IDDM's strokes
                linear = _linear_beliefs(obs, targets, seen_by, test, steps_at, grid)
                linear_probs[at] = linear.to(probs.dtype)
                bar.update()
            bar.close()
            if shared is None:
                say(f"fit: one IDDM per fold on its training strokes ({_fit_words(fits)}; "
                    f"{t_fit:.0f} s)")  # fmt: skip
            say(
                f"learn: LSPI, baselines and MCP decisions on {folds} folds "
                f"({t_learn + t_plan:.0f} s)"
            )

            # every MCP decision executed in SAPIEN
            clock = time.perf_counter()
            dtype = torch.get_default_dtype()
            jobs = [
                (trials[int(i)], movements[int(stop_action[j]) - 1],
                 start_times[int(stop_step[j])], dtype)
                for j, i in enumerate(valid.tolist())
            ]  # fmt: skip
            outcomes = list(
                tqdm(pool.map(_play_rally, jobs), total=n, disable=not progress,
                     desc="play (SAPIEN)", leave=False)
            )  # fmt: skip
            rallies = [
                Rally(int(i), float(trials.targets[i]), job[1], job[2], outcome)
                for i, job, outcome in zip(valid.tolist(), jobs, outcomes, strict=True)
            ]
            t_play = time.perf_counter() - clock
            say(f"play: {n} rallies of the MCP player in SAPIEN ({t_play:.0f} s)")
    finally:
        if executor is None:
            pool.close()
    won["MCP"] = torch.tensor([bool(r.outcome.success) for r in rallies])
    # the scene is deterministic: each live rally must reproduce the reward the stopping
    # problem gave the planner's (step, action) decision
    agree = int((won["MCP"] == (table_reward > 0)).sum())

    table = ResultTable(
        f"hgpdm demo: anticipatory table tennis, {n} test rallies ({folds}-fold cross-fitting "
        f"over {n} of {num_trials} strokes)",
        ["player", "returns", "rate", "95% low", "95% high", "played in"],
        meta={"num_trials": num_trials, "watched": watched, "valid": n, "folds": folds,
              "seed": seed},
    )  # fmt: skip
    for p in players:
        k = int(won[p].sum())
        low, high = return_rate_interval(k, n)
        where = "SAPIEN" if p == "MCP" else "reward table (SAPIEN)"
        table.add(**{"player": p, "returns": k, "rate": k / n, "95% low": low, "95% high": high,
                     "played in": where})  # fmt: skip
    fixed = [p for p in players if p.startswith(FIXED_PREFIXES)]
    best = max(fixed, key=lambda p: int(won[p].sum()))  # first of the best on ties
    diff, low, high = paired_difference_interval(won["MCP"], won[best])
    meta = {
        "best fixed": best,
        "MCP - best fixed": diff,
        "MCP - best fixed 95% low": low,
        "MCP - best fixed 95% high": high,
        "MCP only / best fixed only": f"{int((won['MCP'] & ~won[best]).sum())}/"
        f"{int((~won['MCP'] & won[best]).sum())}",
        "verdict": _verdict(low, high, best, n),
        "simulate [s]": t_sim,
        "fit [s]": t_fit,
        "learn [s]": t_learn,
        "MCP per decision [ms]": 1e3 * t_plan / max(1, decisions),
        "play [s]": t_play,
        "live = table": f"{agree}/{n}",
        "IDDM fits": fits,
    }
    # how far each belief's mean lies from the true target at each decision time
    truth = trials.targets[valid].to(probs.dtype)
    for name, p in (("IDDM", probs), ("linear IDDM", linear_probs)):
        err = 100 * ((p * grid.to(p.dtype)).sum(-1) - truth[:, None]).abs().mean(0)
        meta[f"belief mean MAE [cm], {name}"] = [round(float(e), 1) for e in err]
    table.meta.update(meta)
    return DemoResult(table, rallies, grid, start_times, probs, meta, won, linear_probs)


def _fit_words(fits: list[dict[str, object]]) -> str:
    """``"60 L-BFGS steps, at the step limit"`` for the IDDM fits' summaries (the budget is
    :attr:`AnticipationConfig.fit_steps`; the reasons are in the result's meta)."""
    steps = sorted({f["steps"] for f in fits})
    done = sum(f["converged"] for f in fits)
    state = "converged" if done == len(fits) else (
        "at the step limit" if done == 0 else f"{done} of {len(fits)} converged")  # fmt: skip
    return f"{'/'.join(map(str, steps))} L-BFGS steps, {state}"


def plot_demo(result: DemoResult, out: str | Path) -> list[Path]:
    """Save the return rates with their 95% intervals, one played rally in 3-D and its belief
    over the target (PNGs)."""
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
    fig = Figure(figsize=(8.5, 4.0))
    ax = fig.subplots()
    colours = ["0.7"] * 3 + ["tab:blue"] * 3 + ["tab:orange", "tab:green"]
    bars = ax.bar(range(len(names)), rates, color=colours[: len(names)], yerr=errors, capsize=4,
                  error_kw={"lw": 1, "ecolor": "k"})  # fmt: skip
    best = result.meta.get("best fixed")
    if best in names:
        bars[names.index(best)].set_hatch("//")
    ax.set_xticks(range(len(names)), [n.replace(" ", "\n") for n in names], fontsize=8)
    ax.set_ylabel("return rate on the test rallies\n(exact 95% interval)")
    ax.set_ylim(0, 1)
    title = table.title
    if "MCP - best fixed" in result.meta:
        m = result.meta
        title += (
            f"\nMCP - {m['best fixed']} (hatched), paired: {m['MCP - best fixed']:+.3f} "
            f"[{m['MCP - best fixed 95% low']:+.3f}, {m['MCP - best fixed 95% high']:+.3f}]"
        )
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    paths.append(out / "return_rates.png")
    fig.savefig(paths[-1], dpi=120)

    # the first returned rally (else the first one) and the belief that led to it
    j = next((k for k, r in enumerate(result.rallies) if r.outcome.success), 0)
    rally = result.rallies[j]
    columns = 2 if result.linear_probs is None else 3
    fig = Figure(figsize=(5.5 * columns, 4.2))
    ax3 = fig.add_subplot(1, columns, 1, projection="3d")
    draw_table(ax3)
    draw_stroke(ax3, rally.outcome, WAM(), color=MOVEMENT_COLORS[rally.action], label=rally.action)
    ax3.set_title(
        f"stroke {rally.trial}: {rally.action} started {round(-1000 * rally.start_time)} ms "
        f"before the hit -> {'returned' if rally.outcome.success else 'missed'}",
        fontsize=9,
    )
    beliefs = [("belief (online IDDM, used by the players)", result.target_probs)]
    if result.linear_probs is not None:
        beliefs.append(("belief (linear IDDMs, same strokes)", result.linear_probs))
    for k, (label, probs) in enumerate(beliefs):
        ax = fig.add_subplot(1, 1 + len(beliefs), 2 + k)
        for t, s in enumerate(result.start_times):
            ax.plot(result.grid, probs[j, t], label=f"{round(-1000 * s)} ms before the hit")
        ax.axvline(rally.target, color="k", ls="--", lw=1, label="true target")
        ax.set(xlabel="target x on the hitting plane [m]", ylabel=label)
        ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / "rally.png")
    fig.savefig(paths[-1], dpi=120)
    return paths


def summary(result: DemoResult) -> str:
    """The paired comparison MCP - best fixed strategy as printed under the table."""
    m = result.meta
    return (
        f"MCP - best fixed strategy ({m['best fixed']}), paired over the same rallies: "
        f"{m['MCP - best fixed']:+.3f}, 95% interval [{m['MCP - best fixed 95% low']:+.3f}, "
        f"{m['MCP - best fixed 95% high']:+.3f}] (Newcombe square-and-add; rallies returned by "
        f"MCP only / by {m['best fixed']} only: {m['MCP only / best fixed only']}): "
        f"{m['verdict']}."
    )


def main(argv: list[str]) -> int:
    """CLI entry: ``hgpdm demo [--trials N] [--watched M] [--folds K] [--workers W]
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
        type=non_negative_int,
        default=None,
        help=f"further strokes the IDDM learns from ({DEFAULT_WATCHED})",
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
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--out", type=output_folder, default="hgpdm_demo_output")
    parser.add_argument("--cache-dir", type=output_folder, default=None)
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
    bars = not args.quiet and (args.progress or sys.stderr.isatty())
    if args.full:
        extra = ["--out", str(args.out), "--seed", str(args.seed)]
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

    executor = ant.connect(parser, args.workers, args.ray_address)
    try:
        result = run_demo(
            num_trials=DEFAULT_TRIALS if args.trials is None else args.trials,
            watched=DEFAULT_WATCHED if args.watched is None else args.watched,
            folds=args.folds,
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
    skip = {"best fixed", "MCP - best fixed", "MCP - best fixed 95% low",
            "MCP - best fixed 95% high", "MCP only / best fixed only", "verdict"}  # fmt: skip
    print(", ".join(f"{k}: {v:.3g}" if isinstance(v, float) else f"{k}: {v}"
                    for k, v in result.meta.items() if k not in skip))  # fmt: skip
    out = Path(args.out)
    result.table.to_json(out / "demo.json")
    for path in plot_demo(result, out):
        print(f"saved {path}")
    if not args.quiet:
        status(f"done ({time.perf_counter() - start:.0f} s in all)")
    return 0
