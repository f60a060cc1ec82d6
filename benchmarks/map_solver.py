"""How far Levenberg-Marquardt gets towards the MAP states of a window: the Fisher precision
(Gauss-Newton plus the curvature of the GP variances) against Gauss-Newton alone (issue 30).

``python -m benchmarks map_solver [--quick]`` (about 3 minutes on 2 cores). Writes
``benchmarks/results/map_solver.json``. Needs the Weird Walking training trials in
``../shared/data/cmu`` (seen from the project root).

An H-GPDM and a GPDM are fitted on all 14 Weird Walking training trials with the protocol's
defaults (:data:`~hgpdm_torch.experiments.walkers.DEFAULT_OPTIONS`, 150 MAP steps, Dx = 3); the
first 40 windows of T = 10 (stride 2) of trials 132_01, 132_18 and 132_24 get a missing row
appended (the forecast problem) and :class:`~hgpdm_torch.inference.map.MAPInference` (150
pseudo-inputs; the H-GPDM given the true style) maximises their log joint with each solver for
30 (VB's Laplace start), 50 (the MAP baseline's default) and 300 iterations. Gauss-Newton is the
same solver with the variance's gradient set to zero (its precision then omits exactly the
variance term). Each window's shortfall is measured from the best value either solver reaches
in 300 iterations for that model; the forecast RMSE (the GP mean at the appended row's MAP
state against the recorded next frame) is in-sample: it compares solvers, not methods.
"""

from __future__ import annotations

import contextlib
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import torch

from benchmarks._common import RESULTS, environment
from hgpdm_torch.datasets.cmu import PROTOCOLS, load_protocol
from hgpdm_torch.datasets.walkers import Standardizer
from hgpdm_torch.experiments.style_recognition import forecast_windows
from hgpdm_torch.experiments.walkers import DEFAULT_FIT_STEPS, DEFAULT_OPTIONS
from hgpdm_torch.inference.map import MAPInference
from hgpdm_torch.inference.variational.gaussian_input import GaussianInputGP
from hgpdm_torch.models import GPDM, HGPDM
from hgpdm_torch.results import ResultTable

DATA = Path("../shared/data/cmu")
TRIALS = (0, 6, 11)  # 132_01 (arms out), 132_18 (fast), 132_24 (hopping)


@contextlib.contextmanager
def gauss_newton() -> Iterator[None]:
    """Within the block the GP variance's gradient is zero, so the window's Fisher precision
    is Gauss-Newton's ``J^T J`` (the solver before 2026-12-02)."""
    fisher = GaussianInputGP.predict_point

    def without_variance_curvature(self, mu, *, jacobian=False):
        out = fisher(self, mu, jacobian=jacobian)
        return (*out[:3], torch.zeros_like(out[3])) if jacobian else out

    GaussianInputGP.predict_point = without_variance_curvature
    try:
        yield
    finally:
        GaussianInputGP.predict_point = fisher


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    if not DATA.is_dir():
        print(f"{DATA} not found: the Weird Walking trials are needed (see its README)")
        return 1
    data = load_protocol(PROTOCOLS["weird-walking"], "train", DATA)
    seqs, labels = data.sequences, data.labels
    fit_steps, windows, long = DEFAULT_FIT_STEPS["weird-walking"], 40, 300
    if quick:  # one trial per style, a short fit, a few windows
        pick = [0, 5, 8, 11]
        seqs, labels = [seqs[j] for j in pick], labels[pick]
        fit_steps, windows, long = 10, 6, 60
    std = Standardizer().fit(seqs)
    train = [std.transform(s) for s in seqs]
    options = DEFAULT_OPTIONS["weird-walking"]
    models = {
        "oracle H-GPDM": HGPDM(train, labels, 3, **options),
        "GPDM": GPDM(train, 3, **options),
    }
    fits = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a step budget, as in the experiment
        for name, model in models.items():
            fits[name] = model.fit(fit_steps).summary()
    sel = [j for j in TRIALS if j < len(train)] if not quick else [0, 2, 3]
    z, nxt, y = forecast_windows([train[j] for j in sel], labels[sel], 10, 2)
    z, nxt, y = z[:windows], nxt[:windows], y[:windows]
    z = torch.cat([z, torch.full_like(z[:, :1], float("nan"))], 1)
    table = ResultTable(
        f"MAP states of {z.shape[0]} in-sample Weird Walking windows (T = 10): "
        "Levenberg-Marquardt's shortfall from the best of both solvers after "
        f"{long} iterations, {torch.get_num_threads()} threads",
        [
            "model",
            "solver",
            "iterations",
            "windows > 1 nat short",
            "median short (nats)",
            "90th percentile short (nats)",
            "summed -log joint",
            "forecast RMSE",
            "seconds",
        ],
        meta={**environment(), "quick": quick, "fits": fits, "windows": z.shape[0]},
    )
    levels = torch.tensor([0.5, 0.9], dtype=z.dtype)
    for name, model in models.items():
        engine = MAPInference(model, measurement_points=150)
        kw = {"values": y[:, None]} if isinstance(model, HGPDM) else {}
        runs = {}
        for solver in ("Gauss-Newton (before)", "Fisher (now)"):
            for steps in (30, 50, long):
                with gauss_newton() if solver.startswith("Gauss") else contextlib.nullcontext():
                    start = time.perf_counter()
                    res = engine.infer(z, steps=steps, **kw)
                    seconds = time.perf_counter() - start
                forecast = engine.predict_observations(z, res)[0][:, -1]
                rmse = float((forecast - nxt).pow(2).mean().sqrt())
                runs[solver, steps] = (-res.log_joint[:, 0], rmse, seconds)
        best = torch.minimum(*(f for (_, s), (f, _, _) in runs.items() if s == long))
        for (solver, steps), (f, rmse, seconds) in runs.items():
            short = f - best
            median, p90 = short.quantile(levels).tolist()
            table.add(
                model=name,
                solver=solver,
                iterations=steps,
                **{
                    "windows > 1 nat short": int((short > 1).sum()),
                    "median short (nats)": median,
                    "90th percentile short (nats)": p90,
                    "summed -log joint": float(f.sum()),
                    "forecast RMSE": rmse,
                    "seconds": seconds,
                },
            )
    print(table.to_markdown())
    table.to_json(RESULTS / f"map_solver{'_quick' if quick else ''}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
