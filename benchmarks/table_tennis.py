"""Speed of the simulated table tennis: opponent strokes/s, robot strokes/s, reward-table time.

The thesis's reward table enumerates 270 trials x 3 movements x 5 start times (Sec. 4.3.2).
``python -m benchmarks table_tennis`` samples the trials and plays ``--trials`` of them (default
30; ``--trials 270`` builds the whole table) in one process, and extrapolates the full table's
time from the measured strokes/s; ``--quick`` plays 2 trials (smoke mode, written to
``table_tennis_quick.json``, not tracked). The success rate of each movement and start time is
recorded alongside.
"""

from __future__ import annotations

import os
import tempfile
import time

from benchmarks._common import RESULTS
from hgpdm_torch.experiments.table import ResultTable

N_FULL = 270


def _option(argv: list[str], name: str, default: int) -> int:
    if name in argv:
        return int(argv[argv.index(name) + 1])
    return default


def main(argv: list[str]) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    from hgpdm_torch.robots.table_tennis.strokes import MOVEMENTS
    from hgpdm_torch.robots.table_tennis.trials import (
        DEFAULT_START_TIMES,
        make_trials,
        reward_table,
    )

    torch.set_num_threads(1)
    quick = "--quick" in argv
    n = 2 if quick else _option(argv, "--trials", 30)
    t0 = time.process_time()
    trials = make_trials(n, seed=0)
    sample_s = time.process_time() - t0
    strokes = n * len(MOVEMENTS) * len(DEFAULT_START_TIMES)
    with tempfile.TemporaryDirectory() as cache:
        t0 = time.process_time()
        table = reward_table(trials, cache_dir=cache, progress=not quick)
        play_s = time.process_time() - t0
    per_s = strokes / play_s
    full_s = N_FULL * len(MOVEMENTS) * len(DEFAULT_START_TIMES) / per_s
    how = "measured" if n == N_FULL else f"extrapolated from {n} trials"
    result = ResultTable(
        "Table tennis: opponent sampler and robot strokes (SAPIEN, 1 ms steps, one process, CPU s)",
        ["stage", "count", "cpu s", "per s", "table 270x3x5 [s]", "how"],
    )
    result.add(
        stage="opponent trials (sample_strokes)",
        count=n,
        **{"cpu s": sample_s, "per s": n / sample_s, "table 270x3x5 [s]": None, "how": "measured"},
    )
    result.add(
        stage="robot strokes (reward_table)",
        count=strokes,
        **{"cpu s": play_s, "per s": per_s, "table 270x3x5 [s]": full_s, "how": how},
    )
    rates = (table > 0).double().mean(0)  # [actions, start times]
    result.meta = {
        "command": "python -m benchmarks table_tennis"
        + (" --quick" if quick else f" --trials {n}"),
        "start_times": list(DEFAULT_START_TIMES),
        "success_rate": {
            m: [round(float(r), 3) for r in rates[i]] for i, m in enumerate(MOVEMENTS)
        },
        "best_movement_success": float((table > 0).any(1).double().mean()),
    }
    print(result)
    print("success rate by movement (rows) and start time (columns):", result.meta["success_rate"])
    result.to_json(RESULTS / ("table_tennis_quick.json" if quick else "table_tennis.json"))
    return 0
