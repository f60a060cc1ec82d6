"""Speed of the simulated table tennis: opponent and robot strokes/s, reference vs fast executor.

The thesis's reward table enumerates 270 trials x 3 movements x 5 start times (Sec. 4.3.2).
``python -m benchmarks table_tennis`` (options: ``python -m benchmarks.table_tennis --trials N``)
samples ``--trials`` trials (default 30) in one process and

1. plays the first ``--reference-trials`` of them (default 4, 60 strokes) with the reference
   executor (``execute_stroke(..., reference=True)``: 1 ms PhysX steps throughout, the ball in
   PhysX from the opponent's hit) and with the fast one, each with a fresh planner (nothing
   cached), and reports both strokes/s, their ratio and whether the rewards agree;
2. builds the reward table of all trials with :func:`reward_table` (the planner's cache shares
   the prediction and aiming of a trial between its 15 strokes), and extrapolates the full
   table's time from its strokes/s.

All times are CPU seconds of this process (``time.process_time``), so that other jobs on the
machine disturb them less. ``--quick`` plays 2 trials and 1 reference trial (smoke mode, written to
``table_tennis_quick.json``, not tracked). The success rate of each movement and start time is
recorded alongside.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

from benchmarks._common import RESULTS, environment
from hgpdm_torch.results import ResultTable

N_FULL = 270


def _option(argv: list[str], name: str, default: int) -> int:
    if name in argv:
        return int(argv[argv.index(name) + 1])
    return default


def _executor_times(trials, reference, n_exec: int, ray: bool = True) -> list[dict]:
    """Wall-clock time of the reward table of the first ``n_exec`` trials (empty cache; once
    right after starting the executor, once more with its workers warm) in this process, on 2
    local processes and (``ray``) on a local Ray instance with 2 CPUs (if Ray is installed);
    each table is checked against ``reference`` (the one-process table)."""
    from hgpdm_torch.parallel import ProcessExecutor, RayExecutor, SerialExecutor
    from hgpdm_torch.robots.table_tennis.trials import Trials, reward_table

    ball = trials.ball_after_hit
    subset = Trials(
        trials.obs[:n_exec],
        trials.obs_times,
        trials.targets[:n_exec],
        trials.hit_times[:n_exec],
        type(ball)(*(f[:n_exec] for f in ball)),
    )
    out: list[dict] = []
    makers = [("1 process", SerialExecutor), ("2 local processes", lambda: ProcessExecutor(2))]
    try:
        if ray:
            import ray as _  # noqa: F401

            makers.append(("local Ray, 2 CPUs", lambda: RayExecutor("local", 2)))
    except ImportError:
        print("Ray not installed: the Ray row is skipped")
    for name, make in makers:
        walls = []
        start = time.perf_counter()
        with make() as ex:  # start-up (process pool, Ray instance) counts in the cold run
            for _ in range(2):  # cold workers, then warm ones (each time with an empty cache)
                with tempfile.TemporaryDirectory() as cache:
                    table = reward_table(subset, executor=ex, cache_dir=cache, progress=False)
                walls.append(time.perf_counter() - start)
                start = time.perf_counter()
        out.append(
            {
                "executor": name,
                "trials": n_exec,
                "wall s": walls[0],
                "warm wall s": walls[1],
                "same table": bool((table == reference[:n_exec]).all()),
            }
        )
    for e in out:
        e["x serial"] = out[0]["warm wall s"] / e["warm wall s"]
    return out


def main(argv: list[str]) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    from hgpdm_torch.robots.table_tennis.scene import TableTennisScene
    from hgpdm_torch.robots.table_tennis.strokes import MOVEMENTS, StrokePlanner, execute_stroke
    from hgpdm_torch.robots.table_tennis.trials import (
        DEFAULT_START_TIMES,
        make_trials,
        reward_table,
    )

    torch.set_num_threads(1)
    quick = "--quick" in argv
    n = 2 if quick else _option(argv, "--trials", 30)
    n_reference = min(n, 1 if quick else _option(argv, "--reference-trials", 4))
    per_trial = len(MOVEMENTS) * len(DEFAULT_START_TIMES)
    full = N_FULL * per_trial

    t0 = time.process_time()
    trials = make_trials(n, seed=0)
    sample_s = time.process_time() - t0

    def play(reference: bool) -> tuple[float, list[bool]]:
        planner = StrokePlanner()  # fresh: no prediction, aim or IK cached
        scene = TableTennisScene(wam=planner.wam)
        t0 = time.process_time()
        won = [
            execute_stroke(
                scene, planner, trials[i].ball_after_hit, m, st, reference=reference
            ).success
            for i in range(n_reference)
            for m in MOVEMENTS
            for st in DEFAULT_START_TIMES
        ]
        return time.process_time() - t0, won

    old_s, old_won = play(reference=True)
    new_s, new_won = play(reference=False)
    strokes = n_reference * per_trial
    agree = sum(a == b for a, b in zip(old_won, new_won, strict=True))

    with tempfile.TemporaryDirectory() as cache:
        # builds trials.py's simulator (planner IK, scene) outside the timed table
        reward_table(make_trials(1, seed=1), cache_dir=cache, progress=False)
        t0 = time.process_time()
        table = reward_table(trials, cache_dir=cache, progress=not quick)
        table_s = time.process_time() - t0
    table_per_s = n * per_trial / table_s
    # quick: one trial, no Ray instance (tests/test_parallel.py runs a real one)
    executors = _executor_times(trials, table, n_exec=min(n, 1 if quick else 12), ray=not quick)

    result = ResultTable(
        "Table tennis: opponent sampler and robot strokes (SAPIEN, one process, CPU s)",
        ["stage", "count", "cpu s", "per s", "table 270x3x5 [s]", "how"],
    )

    def row(stage: str, count: int, cpu: float, how: str, per_table: bool = True) -> None:
        values = {"cpu s": cpu, "per s": count / cpu}
        values["table 270x3x5 [s]"] = full * cpu / count if per_table else None
        result.add(stage=stage, count=count, how=how, **values)

    row("opponent trials (sample_strokes)", n, sample_s, "measured", per_table=False)
    row(
        "robot strokes, reference (reference=True, 1 ms)",
        strokes,
        old_s,
        f"{n_reference} trials, extrapolated",
    )
    row(
        "robot strokes, current (execute_stroke)",
        strokes,
        new_s,
        f"same {n_reference} trials, nothing cached, extrapolated",
    )
    row(
        "robot strokes, current (reward_table)",
        n * per_trial,
        table_s,
        "measured" if n == N_FULL else f"{n} trials, extrapolated",
    )
    rates = (table > 0).double().mean(0)  # [actions, start times]
    result.meta = {
        "command": "python -m benchmarks table_tennis --quick"
        if quick
        else f"python -m benchmarks.table_tennis --trials {n} --reference-trials {n_reference}",
        "speedup_same_strokes": old_s / new_s,
        "speedup_reward_table": table_per_s / (strokes / old_s),
        "rewards_agree": f"{agree} of {strokes} strokes",
        "reward_table_s": table_s,
        "start_times": list(DEFAULT_START_TIMES),
        "success_rate": {
            m: [round(float(r), 3) for r in rates[i]] for i, m in enumerate(MOVEMENTS)
        },
        "best_movement_success": float((table > 0).any(1).double().mean()),
        "executors": executors,
        "load_average": os.getloadavg(),
        **environment(),
    }
    print(result)
    print(
        f"strokes/s previous {strokes / old_s:.3g}, current {strokes / new_s:.3g} "
        f"(x{old_s / new_s:.1f} on the same {strokes} strokes; reward_table "
        f"{table_per_s:.3g}/s, x{result.meta['speedup_reward_table']:.1f}); rewards agree on "
        f"{agree} of {strokes}; reward table of {n} trials: {table_s:.1f} CPU s"
    )
    print("success rate by movement (rows) and start time (columns):", result.meta["success_rate"])
    for e in executors:
        print(
            f"reward table of {e['trials']} trials on {e['executor']}: {e['wall s']:.1f} s wall "
            f"with start-up, {e['warm wall s']:.1f} s warm (x{e['x serial']:.2f} the one-process "
            f"speed), same table: {e['same table']}"
        )
    result.to_json(RESULTS / ("table_tennis_quick.json" if quick else "table_tennis.json"))
    return 0


if __name__ == "__main__":  # python -m benchmarks.table_tennis [--quick] [--trials N] ...
    raise SystemExit(main(sys.argv[1:]))
