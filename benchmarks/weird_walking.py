"""Wall time of ``hgpdm walkers --protocol weird-walking --test-data FOLDER`` (issue 30: within
15 minutes on 2 cores, both window lengths, stride 2).

``python -m benchmarks weird_walking [--quick]`` (about 11 minutes on 2 cores with the
protocol's defaults: Dx = 10, each frame beside the previous one, the learned measurement width,
150 pseudo-inputs, 150 MAP steps).
Writes ``benchmarks/results/weird_walking.json``. Needs the Weird Walking training trials in
``../shared/data/cmu`` (seen from the project root).

The thesis's test trials are held back from this project, so the run scores stand-ins of the
same lengths: each test trial name (132_06-12, 20-22, 26-28, 48-50) is linked, in a temporary
folder, to a training trial of the same style (arms out 01-05, 01, 02; fast 17-19; hopping
23-25; slow 45-47). The models are fitted on all 14 training trials as in the real command, so
the RMSEs of this run are in-sample and mean nothing; only the times are reported: the two MAP
fits, and per window length the number of windows and the seconds of all forecasts (VB and MAP
of both models, ridge AR, the GRU's CV and fit), with the command's defaults (the sparse
measurement GP on the protocol's ``walkers.DEFAULT_MEASUREMENT_POINTS`` pseudo-inputs).
"""

from __future__ import annotations

import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

from benchmarks._common import RESULTS, environment
from hgpdm_torch.datasets.cmu import PROTOCOLS
from hgpdm_torch.experiments.walkers import walkers
from hgpdm_torch.results import ResultTable

DATA = Path("../shared/data/cmu")
#: training trial standing in for each test trial (same style, similar length)
ARMS_OUT = zip(range(6, 13), (1, 2, 3, 4, 5, 1, 2), strict=True)
STAND_INS = {
    **{f"132_{t:02d}": f"132_{s:02d}" for t, s in ARMS_OUT},
    **{f"132_{t:02d}": f"132_{t - 3:02d}" for t in (20, 21, 22, 26, 27, 28, 48, 49, 50)},
}


def stand_in_folder(folder: Path, trials: list[str]) -> None:
    """Link each test trial name in ``trials`` to its stand-in's AMC file in ``DATA``."""
    (folder / "132.asf").symlink_to((DATA / "132.asf").resolve())
    for name in trials:
        (folder / f"{name}.amc").symlink_to((DATA / f"{STAND_INS[name]}.amc").resolve())


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    if not DATA.is_dir():
        print(f"{DATA} not found: the Weird Walking trials are needed (see its README)")
        return 1
    test = [t for t, _ in PROTOCOLS["weird-walking"].test]
    options = {"lengths": (5, 10), "stride": 2}
    if quick:  # one stand-in per style, short windows and fits
        test = ["132_06", "132_20", "132_26", "132_48"]
        options = {"lengths": (5,), "stride": 8, "fit_steps": 10}
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the fits' step-limit warnings
        stand_in_folder(Path(tmp), test)
        start = time.perf_counter()
        result = walkers("weird-walking", folder=DATA, test_folder=tmp, **options)
        total = time.perf_counter() - start
    fits = result.meta["fits"][0]
    table = ResultTable(
        "hgpdm walkers --protocol weird-walking --test-data (stand-ins of the test trials): "
        f"wall time, {torch.get_num_threads()} threads",
        ["part", "windows", "seconds"],
        meta={
            **environment(),
            "quick": quick,
            "target seconds": 900,
            **options,
            "model_options": result.meta["model_options"],
            "fit_steps": result.meta["fit_steps"],
            "latent_dim": result.meta["latent_dim"],
            "features": result.meta["features"],
            "measurement_points": result.meta["measurement_points"],
        },
    )
    table.add(part="two MAP fits", windows=None, seconds=fits["seconds"])
    for T in options["lengths"]:
        windows = sum(r["windows"] for r in result.rows if r["T"] == T and r["trial"] in test)
        table.add(part=f"forecasts T={T}", windows=windows, seconds=fits[f"forecast seconds T={T}"])
    table.add(part="whole command", windows=None, seconds=total)
    print(table.to_markdown(".1f"))
    table.to_json(RESULTS / f"weird_walking{'_quick' if quick else ''}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
