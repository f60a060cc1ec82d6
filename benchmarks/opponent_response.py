"""Time per delta-safe response (Problem 38) in online play; the thesis needed < 50 ms a serve.

``python -m benchmarks opponent_response [--quick]``. Writes
``benchmarks/results/opponent_response.json`` (``..._quick.json`` with ``--quick``).

Each scenario replays an opponent stream and re-solves Problem (38) after every observation,
as Algorithm 5.1 does while it fills its sample set: the warm-started projected sub-gradient
solver (the online method), the same solver started cold from minimax, and the cutting-plane
solver that certifies the optimum, all in this process. Times are medians per response
(the mean and 95th percentile of the warm solver too: a few responses need the cutting-plane
fallback, counted in "fallback [%]"); "max gap / tol" is the largest certified gap
``upper_bound - value`` of the warm solver over its guaranteed tolerance (at most 1), "value
gap" the largest shortfall of its value below the cutting planes' (certified to 1e-7).
Target: <= 1 ms median per response.
"""

from __future__ import annotations

import platform
import statistics
import time

import numpy as np

from benchmarks._common import RESULTS
from hgpdm_torch.decision.games import RPS_REWARD, TABLE_TENNIS_REWARD
from hgpdm_torch.decision.opponent import DeltaSafeResponder, solve_delta_safe
from hgpdm_torch.results import ResultTable

SCENARIOS = {
    "RPS vs [0.6, 0.2, 0.2]": (RPS_REWARD, (0.6, 0.2, 0.2)),
    "serves, uniform": (TABLE_TENNIS_REWARD, (1 / 3, 1 / 3, 1 / 3)),
    "serves, forehand side": (TABLE_TENNIS_REWARD, (0.7, 0.2, 0.1)),
    "random 5x5": (np.random.default_rng(0).normal(size=(5, 5)), (0.4, 0.3, 0.1, 0.1, 0.1)),
}


def _stream(reward: np.ndarray, truth: tuple[float, ...], n: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    counts = np.zeros(reward.shape[1], dtype=int)
    out = []
    for a in rng.choice(len(truth), size=n, p=truth):
        counts[a] += 1
        out.append(counts.copy())
    return out


def _timed(fn, stream: list[np.ndarray]) -> tuple[list[float], list[float]]:
    times, values = [], []
    for counts in stream:
        start = time.perf_counter()
        values.append(fn(counts))
        times.append(time.perf_counter() - start)
    return times, values


def run(n_games: int, delta: float = 0.1) -> ResultTable:
    table = ResultTable(
        "Delta-safe response time per game (float64, 1 thread), median over a stream",
        ["scenario", "games", "warm [ms]", "mean warm [ms]", "p95 warm [ms]", "cold [ms]",
         "exact [ms]", "exact / warm", "mean steps", "fallback [%]", "max gap / tol",
         "value gap"],
        meta={"delta": delta, "machine": platform.processor() or platform.machine(),
              "python": platform.python_version(), "target_ms": 1.0, "thesis_ms": 50.0},
    )  # fmt: skip
    for name, (reward, truth) in SCENARIOS.items():
        stream = _stream(reward, truth, n_games, seed=1)
        warm = DeltaSafeResponder(reward)
        steps: list[int] = []
        planes: list[int] = []
        gaps: list[float] = []

        def warm_fn(c, warm=warm, steps=steps, planes=planes, gaps=gaps):
            res = warm.respond(c, delta)
            steps.append(res.iterations)
            planes.append(res.cutting_planes)
            gaps.append(res.upper_bound - res.value)
            return res.value

        cold = DeltaSafeResponder(reward)

        def cold_fn(c, cold=cold):
            cold.reset()
            return cold.respond(c, delta).value

        t_warm, v_warm = _timed(warm_fn, stream)
        t_cold, _ = _timed(cold_fn, stream)
        t_exact, v_exact = _timed(lambda c, r=reward: solve_delta_safe(r, c, delta).value, stream)
        gap = max(e - w for e, w in zip(v_exact, v_warm, strict=True))
        med = statistics.median
        table.add(
            scenario=name, games=n_games, **{
                "warm [ms]": 1e3 * med(t_warm),
                "mean warm [ms]": 1e3 * float(np.mean(t_warm)),
                "p95 warm [ms]": 1e3 * float(np.quantile(t_warm, 0.95)),
                "cold [ms]": 1e3 * med(t_cold),
                "exact [ms]": 1e3 * med(t_exact),
                "exact / warm": med(t_exact) / med(t_warm),
                "mean steps": float(np.mean(steps)),
                "fallback [%]": 100.0 * float(np.mean(np.array(planes) > 0)),
                "max gap / tol": max(gaps) / (warm.tol * float(np.ptp(reward))),
                "value gap": max(gap, 0.0),
            },
        )  # fmt: skip
    return table


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    table = run(n_games=60 if quick else 600)
    print(table.to_markdown())
    table.to_json(RESULTS / ("opponent_response_quick.json" if quick else "opponent_response.json"))
    return 0
