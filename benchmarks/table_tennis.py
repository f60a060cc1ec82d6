"""Speed of the simulated table-tennis trials: strokes per second and the reward-table time.

The thesis's reward table enumerates 270 trials x 3 movements x 5 start times (Sec. 4.3.2). The
full run builds it (single process); ``--quick`` times a few trials and extrapolates, and says so.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from hgpdm_torch.experiments.table import ResultTable

RESULTS = Path(__file__).parent / "results" / "table_tennis.json"


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
    torch.set_default_dtype(torch.float64)
    quick = "--quick" in argv
    n_full = 270
    n = 3 if quick else n_full
    trials = make_trials(n, seed=0)
    strokes = n * len(MOVEMENTS) * len(DEFAULT_START_TIMES)
    with tempfile.TemporaryDirectory() as cache:
        t0 = time.perf_counter()
        table = reward_table(trials, cache_dir=cache, progress=not quick)
        elapsed = time.perf_counter() - t0
    per_s = strokes / elapsed
    full = n_full * len(MOVEMENTS) * len(DEFAULT_START_TIMES) / per_s
    result = ResultTable(
        "Table tennis: simulated strokes (SAPIEN, 1 ms steps, one process)",
        ["trials", "strokes", "seconds", "strokes/s", "table 270x3x5 [s]", "how"],
    )
    result.add(
        trials=n,
        strokes=strokes,
        seconds=elapsed,
        **{
            "strokes/s": per_s,
            "table 270x3x5 [s]": full,
            "how": "extrapolated from --quick" if quick else "measured",
        },
    )
    result.meta = {
        "command": "python -m benchmarks table_tennis" + (" --quick" if quick else ""),
        "success_rate": float((table > 0).double().mean()),
    }
    print(result)
    result.to_json(RESULTS)
    return 0
