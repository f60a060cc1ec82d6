"""Sec. 5.4: delta-safe strategies in rock-paper-scissors and when returning table-tennis serves.

Four experiments, each returning a :class:`ResultTable` (per-game curves go in ``meta``):

- :func:`stationary_rps` (Fig. 5.1): estimated and true reward against ``[0.6, 0.2, 0.2]`` for
  sample sizes from 1 to 1e8; counts are drawn as one multinomial per run.
- :func:`switching_rps` (Fig. 5.2): Algorithm 5.1 with and without change detection when the
  opponent switches from ``[0.8, 0.1, 0.1]`` to ``[0.1, 0.1, 0.8]``; detection delays and the
  false-alarm rate against an opponent that never switches.
- :func:`two_stage_rps_experiment` (Fig. 5.3): delta-safe backward induction against the
  opponent of Table 5.2.
- :func:`table_tennis_serves` (Fig. 5.5-5.7): average expected reward (AER) of delta-safe play,
  minimax and the pure strategies against three simulated volunteers, with Table 5.3 rewards.

Command line: ``hgpdm games {stationary,switch,two-stage,serves} [--quick] [--seed S]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import numpy as np

from hgpdm_torch.decision.games import (
    RPS_REWARD,
    SERVE_ACTIONS,
    TABLE_TENNIS_REWARD,
    best_response,
    fictitious_play,
    minimax_strategy,
    two_stage_rps,
)
from hgpdm_torch.decision.opponent import AdaptiveLearner, DeltaSafeResponder, delta_safe_tree
from hgpdm_torch.experiments.arguments import output_file, random_seed
from hgpdm_torch.results import ResultTable

from ..progress import tqdm
from .arguments import SMOKE

__all__ = [
    "TABLE_5_2",
    "VOLUNTEERS",
    "main",
    "stationary_rps",
    "switching_rps",
    "table_tennis_serves",
    "two_stage_rps_experiment",
]


#: Table 5.2: the opponent's local strategies in the two-stage game, state s_0 then s_1..s_9
#: (state ``1 + 3 a_i + a_j`` follows the Stage-1 joint action, actions rock, paper, scissors).
TABLE_5_2 = (
    (0.6, 0.2, 0.2),
    (1 / 3, 1 / 3, 1 / 3),
    (0.2, 0.6, 0.2),
    (0.4, 0.4, 0.2),
    (0.2, 0.4, 0.4),
    (1 / 3, 1 / 3, 1 / 3),
    (0.2, 0.2, 0.6),
    (0.6, 0.2, 0.2),
    (0.4, 0.2, 0.4),
    (1 / 3, 1 / 3, 1 / 3),
)

#: Simulated volunteers of Sec. 5.4.2: serve-region distributions (forehand side, middle,
#: backhand side), and for the switching one the serve after which it changes.
VOLUNTEERS: dict[str, tuple[tuple[float, ...], tuple[float, ...], int]] = {
    "uniform": ((1 / 3, 1 / 3, 1 / 3), (1 / 3, 1 / 3, 1 / 3), 0),
    "forehand-side": ((0.7, 0.2, 0.1), (0.7, 0.2, 0.1), 0),
    "switching": ((0.8, 0.15, 0.05), (0.05, 0.45, 0.5), 85),
}


def _log_grid(high: float, per_decade: int = 2) -> list[int]:
    sizes = np.round(np.logspace(0, np.log10(high), int(np.log10(high)) * per_decade + 1))
    return sorted({int(s) for s in sizes})


def stationary_rps(
    sample_sizes: Sequence[int] | None = None,
    repeats: int = 20,
    opponent: Sequence[float] = (0.6, 0.2, 0.2),
    delta: float = 0.1,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Fig. 5.1: delta-safe play against a stationary opponent over growing sample sizes.

    For each size ``N`` and repeat, the opponent's ``N`` actions are one multinomial draw; the
    learner answers with Problem (38) (sub-gradient solver). "Estimated" is the worst case over
    the ball (the delta-safe lower bound), "true" the reward against the real opponent.
    Fictitious play on the same counts is shown for contrast.

    Returns:
        One row per sample size: mean/min/max of estimated and true reward, the fraction of
        repeats where the bound held, fictitious play's mean and worst true reward, and the
        optimal (best-response) reward.
    """
    sizes = list(sample_sizes) if sample_sizes is not None else _log_grid(1e8)
    truth = np.asarray(opponent, dtype=float)
    optimal = float(best_response(RPS_REWARD, truth) @ RPS_REWARD @ truth)
    rng = np.random.default_rng(seed)
    responder = DeltaSafeResponder(RPS_REWARD)
    table = ResultTable(
        "Fig. 5.1: delta-safe play against a stationary RPS opponent",
        ["n_samples", "estimated_mean", "estimated_min", "estimated_max", "true_mean",
         "true_min", "true_max", "bound_held", "fp_true_mean", "fp_true_min", "optimal"],
        meta={"opponent": truth.tolist(), "delta": delta, "repeats": repeats, "seed": seed},
    )  # fmt: skip
    for n in tqdm(sizes, disable=not progress, desc="sample sizes"):
        est, true, fp = [], [], []
        for _ in range(repeats):
            counts = rng.multinomial(n, truth)
            responder.reset()
            res = responder.respond(counts, delta)
            est.append(res.value)
            true.append(float(res.strategy @ RPS_REWARD @ truth))
            fp.append(float(fictitious_play(RPS_REWARD, counts) @ RPS_REWARD @ truth))
        est_a, true_a = np.array(est), np.array(true)
        table.add(
            n_samples=n, estimated_mean=est_a.mean(), estimated_min=est_a.min(),
            estimated_max=est_a.max(), true_mean=true_a.mean(), true_min=true_a.min(),
            true_max=true_a.max(), bound_held=float(np.mean(true_a >= est_a - 1e-12)),
            fp_true_mean=float(np.mean(fp)), fp_true_min=float(np.min(fp)), optimal=optimal,
        )  # fmt: skip
    return table


def _play(
    learner: AdaptiveLearner, truths: np.ndarray, actions: np.ndarray, reward: np.ndarray
) -> np.ndarray:
    """Play ``len(actions)`` games; returns the true expected reward of each game ``[T]``."""
    out = np.empty(len(actions))
    for t, a_j in enumerate(actions):
        out[t] = learner.strategy @ reward @ truths[t]
        learner.observe(int(a_j))
    return out


def switching_rps(
    n_games: int = 3000,
    switch_at: int = 1000,
    before: Sequence[float] = (0.8, 0.1, 0.1),
    after: Sequence[float] = (0.1, 0.1, 0.8),
    n_min: int = 256,
    delta: float = 0.1,
    alpha: float = 0.01,
    repeats: int = 20,
    window: int = 100,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Fig. 5.2: Algorithm 5.1 with and without change detection across a strategy switch.

    Each repeat plays ``n_games`` against an opponent that switches after ``switch_at`` games,
    once with the two-sample tests and once without, on the same opponent actions; a third run
    against an opponent that never switches counts false alarms.

    Returns:
        One row per window of games: mean true reward with and without detection and the
        optimal reward. ``meta`` holds the per-game mean curves, detection delays (games from
        the switch to the first reset after it), the detection rate within three blocks and the
        false-alarm rate (resets per test against the stationary opponent).
    """
    rng = np.random.default_rng(seed)
    b, a = np.asarray(before, dtype=float), np.asarray(after, dtype=float)
    truths = np.where((np.arange(n_games) < switch_at)[:, None], b, a)
    curves = {"with_detection": [], "without_detection": []}
    delays, alarms, tests = [], 0, 0
    for _ in tqdm(range(repeats), disable=not progress, desc="repeats"):
        actions = np.array([rng.choice(3, p=p) for p in truths])
        for key, detect in (("with_detection", True), ("without_detection", False)):
            learner = AdaptiveLearner(RPS_REWARD, delta, n_min, alpha, change_detection=detect)
            curves[key].append(_play(learner, truths, actions, RPS_REWARD))
            if detect:
                late = [r - switch_at for r in learner.resets if r >= switch_at]
                delays.append(late[0] if late else np.inf)
        still = np.repeat(b[None], n_games, axis=0)
        learner = AdaptiveLearner(RPS_REWARD, delta, n_min, alpha)
        _play(learner, still, rng.choice(3, size=n_games, p=b), RPS_REWARD)
        alarms += len(learner.resets)
        tests += _n_tests(learner.resets, n_games, n_min)
    mean = {k: np.mean(v, axis=0) for k, v in curves.items()}
    optimal = np.array([best_response(RPS_REWARD, p) @ RPS_REWARD @ p for p in truths])
    delays_a = np.array(delays, dtype=float)
    table = ResultTable(
        "Fig. 5.2: true reward per game across a strategy switch (window means)",
        ["games", "with_detection", "without_detection", "optimal"],
        meta={
            "n_min": n_min, "delta": delta, "alpha": alpha, "repeats": repeats, "seed": seed,
            "switch_at": switch_at,
            "curves": {k: v.tolist() for k, v in mean.items()} | {"optimal": optimal.tolist()},
            "detection_delay_mean": float(np.mean(delays_a[np.isfinite(delays_a)]))
            if np.isfinite(delays_a).any() else None,
            "detection_delay_max": float(delays_a.max()),
            "detected_within_3_blocks": float(np.mean(delays_a <= 3 * n_min)),
            "false_alarm_rate_per_test": alarms / max(tests, 1),
            "false_alarm_tests": tests,
        },
    )  # fmt: skip
    for start in range(0, n_games, window):
        sl = slice(start, min(start + window, n_games))
        table.add(
            games=sl.stop, with_detection=float(mean["with_detection"][sl].mean()),
            without_detection=float(mean["without_detection"][sl].mean()),
            optimal=float(optimal[sl].mean()),
        )  # fmt: skip
    return table


def _n_tests(resets: list[int], n_games: int, n_min: int) -> int:
    """How many two-sample tests Algorithm 5.1 ran in ``n_games`` given its reset games."""
    count, start = 0, 0
    for stop in [*resets, n_games - 1]:
        played = stop - start + 1
        count += max(0, (played - n_min) // n_min)
        start = stop + 1
    return count


def two_stage_rps_experiment(
    sample_sizes: Sequence[int] | None = None,
    repeats: int = 20,
    delta: float = 0.1,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Fig. 5.3: delta-safe backward induction in two-stage RPS against Table 5.2.

    Data come from ``N`` two-stage games in which Player i explores uniformly at the root, so
    every Stage-2 state is visited; all counts are multinomial draws (root joint actions, then
    the opponent's actions in each child).

    Returns:
        One row per ``N``: mean/min/max of the estimated (root delta-safe value) and true
        return, the fraction of repeats where the bound held, and the globally optimal return.
    """
    sizes = list(sample_sizes) if sample_sizes is not None else _log_grid(1e6)
    game = two_stage_rps()
    opponents = [np.asarray(p) for p in TABLE_5_2]
    optimal = float(game.best_response(opponents)[1][0])
    rng = np.random.default_rng(seed)
    table = ResultTable(
        "Fig. 5.3: two-stage RPS against the opponent of Table 5.2",
        ["n_games", "estimated_mean", "estimated_min", "estimated_max", "true_mean", "true_min",
         "true_max", "bound_held", "optimal"],
        meta={"delta": delta, "repeats": repeats, "seed": seed, "exploration": "uniform"},
    )  # fmt: skip
    for n in tqdm(sizes, disable=not progress, desc="sample sizes"):
        est, true = [], []
        for _ in range(repeats):
            joint = rng.multinomial(n, np.outer(np.full(3, 1 / 3), opponents[0]).ravel())
            counts = [joint.reshape(3, 3).sum(0)]
            counts += [rng.multinomial(m, opponents[1 + k]) for k, m in enumerate(joint)]
            res = delta_safe_tree(game, counts, delta)
            est.append(res.values[0])
            true.append(game.values(res.strategies, opponents)[0])
        est_a, true_a = np.array(est), np.array(true)
        table.add(
            n_games=n, estimated_mean=est_a.mean(), estimated_min=est_a.min(),
            estimated_max=est_a.max(), true_mean=true_a.mean(), true_min=true_a.min(),
            true_max=true_a.max(), bound_held=float(np.mean(true_a >= est_a - 1e-9)),
            optimal=optimal,
        )  # fmt: skip
    return table


def table_tennis_serves(
    volunteer: str = "uniform",
    n_serves: int = 150,
    repeats: int = 50,
    n_min: int = 20,
    delta: float = 0.1,
    alpha: float = 0.01,
    every: int = 10,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Fig. 5.5-5.7: returning serves of a simulated volunteer with the rewards of Table 5.3.

    Each serve lands in a region drawn from the volunteer's distribution; whether each of the
    robot's three poses would return it is a Bernoulli draw with the Table 5.3 success rate, as
    the low-level planner's three binary outputs in the thesis. A strategy earns its probability
    of a successful return; AER is the running mean over serves, averaged over ``repeats``
    sessions. All strategies see the same serves.

    Returns:
        One row per ``every`` serves: AER of delta-safe play with and without change detection,
        minimax, and each pure strategy. ``meta`` holds the full curves and, for delta-safe play
        with and without detection, the mean over sessions of its final AER minus minimax's on
        the same serves, with its standard error.
    """
    if volunteer not in VOLUNTEERS:
        raise ValueError(f"unknown volunteer {volunteer!r}; expected one of {list(VOLUNTEERS)}")
    before, after, switch = VOLUNTEERS[volunteer]
    r = TABLE_TENNIS_REWARD
    truths = np.array([after if switch and t >= switch else before for t in range(n_serves)])
    pi_mm = minimax_strategy(r)[0]
    names = ["delta_safe_detection", "delta_safe", "minimax"] + [f"pure_{a}" for a in SERVE_ACTIONS]
    rewards = {k: np.zeros((repeats, n_serves)) for k in names}  # [session, serve]
    rng = np.random.default_rng(seed)
    for i in tqdm(range(repeats), disable=not progress, desc="sessions"):
        regions = np.array([rng.choice(3, p=p) for p in truths])
        success = rng.random((n_serves, 3)) < r[:, regions].T  # [T, robot action]
        learners = {
            "delta_safe_detection": AdaptiveLearner(r, delta, n_min, alpha),
            "delta_safe": AdaptiveLearner(r, delta, n_min, alpha, change_detection=False),
        }
        for t in range(n_serves):
            for key, learner in learners.items():
                rewards[key][i, t] = learner.strategy @ success[t]
                learner.observe(int(regions[t]))
        rewards["minimax"][i] = success @ pi_mm
        for k, a in enumerate(SERVE_ACTIONS):
            rewards[f"pure_{a}"][i] = success[:, k]
    totals = {k: v.sum(0) for k, v in rewards.items()}
    aer = {k: np.cumsum(v / repeats) / np.arange(1, n_serves + 1) for k, v in totals.items()}
    # each session's AER after all serves, paired against minimax (the same serves)
    final = {k: v.mean(1) for k, v in rewards.items()}
    paired = {}
    for k in ("delta_safe_detection", "delta_safe"):
        diff = final[k] - final["minimax"]
        paired[f"{k} - minimax"] = float(diff.mean())
        paired[f"{k} - minimax SEM"] = float(diff.std(ddof=1) / np.sqrt(repeats))
    table = ResultTable(
        f"Fig. 5.5-5.7: average expected reward against the {volunteer} volunteer",
        ["serves", *names],
        meta={
            "volunteer": volunteer, "before": before, "after": after, "switch": switch,
            "n_min": n_min, "delta": delta, "alpha": alpha, "repeats": repeats, "seed": seed,
            **paired, "curves": {k: v.tolist() for k, v in aer.items()},
        },
    )  # fmt: skip
    for t in range(every, n_serves + 1, every):
        table.add(serves=t, **{k: float(v[t - 1]) for k, v in aer.items()})
    return table


def main(argv: list[str]) -> int:
    """``hgpdm games EXPERIMENT [--quick] [--seed S] [--json PATH]``."""
    parser = argparse.ArgumentParser(prog="hgpdm games", description=__doc__.splitlines()[0])
    parser.add_argument("experiment", choices=["stationary", "switch", "two-stage", "serves"])
    parser.add_argument("--quick", action="store_true", help="small sizes (also HGPDM_SMOKE=1)")
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument(
        "--json", type=output_file, help="also write the table(s) as JSON to this path"
    )
    args = parser.parse_args(argv)
    quick = args.quick or SMOKE
    if args.experiment == "stationary":
        sizes = _log_grid(1e4) if quick else None
        tables = [stationary_rps(sizes, repeats=5 if quick else 20, seed=args.seed, progress=True)]
    elif args.experiment == "switch":
        kw = {"n_games": 600, "switch_at": 200, "n_min": 64, "repeats": 3} if quick else {}
        tables = [switching_rps(seed=args.seed, progress=True, **kw)]
    elif args.experiment == "two-stage":
        sizes = _log_grid(1e3) if quick else None
        tables = [
            two_stage_rps_experiment(
                sizes, repeats=3 if quick else 20, seed=args.seed, progress=True
            )
        ]
    else:
        tables = [
            table_tennis_serves(v, repeats=5 if quick else 50, seed=args.seed, progress=True)
            for v in VOLUNTEERS
        ]
    for i, table in enumerate(tables):
        print(table.to_markdown())
        print({k: v for k, v in table.meta.items() if k != "curves"})
        if args.json:
            path = args.json if len(tables) == 1 else args.json.with_stem(f"{args.json.stem}_{i}")
            table.to_json(path)
    return 0
