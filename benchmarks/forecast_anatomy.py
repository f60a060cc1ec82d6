"""Where the GP forecasts of walking lose to ridge AR: how far held-out poses lie from the
models' latent manifold, against the forecast errors (issue 30).

``python -m benchmarks forecast_anatomy [--quick] [--protocols=walkers,weird-walking] [--dx3]``
(about 3 minutes for Walkers' 7 folds and 12 for Weird Walking's 4 on 2 cores). Writes
``benchmarks/results/forecast_anatomy.json`` (``forecast_anatomy_dx3.json`` with ``--dx3``).
Needs ``../shared/data/cmu`` (seen from the project root).

Each protocol runs the leave-one-trial-out folds of ``hgpdm walkers`` (all 7 on Walkers, the
4 of ``--max-folds 4`` on Weird Walking) with the command's defaults: an H-GPDM and a GPDM
fitted with the protocol's latent dimension, options, pseudo-input count and step count
(:data:`~hgpdm_torch.experiments.walkers.DEFAULT_LATENT_DIM` and its siblings; Dx = 3 on
both protocols with ``--dx3``, the thesis's) on the poses alone (the thesis's observations,
whose manifold this measures; the command's velocity features, where its CV chose them, are
not used here), and ridge AR with its order and penalty by grouped CV. Per held-out trial and
window length T (windows every 2 frames), the RMSE over the standardised channels of:

- the forecasts: ``ridge AR``, ``ridge AR order 1`` (the last frame only, its penalty by the
  same CV: what ridge AR gains from the frame before, i.e. from the velocity), ``repeat last
  frame``, ``H-GPDM VB`` (the ML style's forecast,
  the thesis's: the joint ``q(z)`` conditioned on the window), ``H-GPDM VB + AR(1)`` (with the
  residual of :func:`~hgpdm_torch.inference.residual.ar1_residual_forecast`, the command's best
  H-GPDM forecast), ``GPDM VB + AR(1)``, and ``H-GPDM + AR(1) / ridge mean`` (the two
  forecasts' average: whether the GP forecast holds information that ridge AR lacks);
- how well the model reconstructs poses of the held-out trial: ``H-GPDM recon. z_T`` (the
  window's last observed frame from the window's own ``q(x_T)``, the per-step marginal mean under
  the ML style) and ``H-GPDM recon. z_T+1 seen`` (the next frame, inferred with that frame
  observed too: what the manifold can do at best for the frame to forecast);
- ``PCA-k recon.``: the held-out trial's frames projected on the top k principal directions of
  the training frames (k = 3, 8, 20), the linear manifold's floor of each size.

The ``mean`` rows average over held-out trials, the ``SEM`` rows give the standard error.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch

from benchmarks._common import RESULTS, environment
from hgpdm_torch.baselines import LastFrameForecaster, RidgeAR
from hgpdm_torch.datasets.cmu import PROTOCOLS, load_protocol
from hgpdm_torch.datasets.walkers import Standardizer
from hgpdm_torch.experiments.intervals import mean_sem
from hgpdm_torch.experiments.style_recognition import forecast_windows
from hgpdm_torch.experiments.walkers import (
    DEFAULT_FIT_STEPS,
    DEFAULT_LATENT_DIM,
    DEFAULT_MEASUREMENT_POINTS,
    DEFAULT_OPTIONS,
    FORECAST_PROTOCOLS,
    LAPLACE_STEPS,
    loto_folds,
    spread_folds,
)
from hgpdm_torch.inference.variational import VariationalInference
from hgpdm_torch.inference.variational.prediction import candidate_forecasts
from hgpdm_torch.models import GPDM, HGPDM
from hgpdm_torch.results import ResultTable

DATA = Path("../shared/data/cmu")
#: held-out folds per protocol: every one on Walkers, one per style on Weird Walking (the CV of
#: the walking page)
MAX_FOLDS = {"walkers": None, "weird-walking": 4}
PCA_DIMS = (3, 8, 20)
FORECASTS = (
    "ridge AR",
    "ridge AR order 1",
    "repeat last frame",
    "H-GPDM VB",
    "H-GPDM VB + AR(1)",
    "GPDM VB + AR(1)",
    "H-GPDM + AR(1) / ridge mean",
)
RECONSTRUCTIONS = (
    "H-GPDM recon. z_T",
    "H-GPDM recon. z_T+1 seen",
    *(f"PCA-{k} recon." for k in PCA_DIMS),
)
COLUMNS = ("protocol", "Dx", "held out", "T", "windows", *FORECASTS, *RECONSTRUCTIONS)


def _rmse(pred: torch.Tensor, truth: torch.Tensor) -> float:
    return float((pred - truth).pow(2).mean().sqrt())


def pca_reconstruction_rmse(train: torch.Tensor, test: torch.Tensor, k: int) -> float:
    """RMSE of ``test [N, D]`` projected on the top ``k`` principal directions of ``train [M, D]``
    (both centred on the training mean)."""
    mean = train.mean(0)
    basis = torch.linalg.svd(train - mean, full_matrices=False)[2][:k]  # [k, D]
    centred = test - mean
    return _rmse(centred @ basis.T @ basis, centred)


def _score_fold(
    tr: list[torch.Tensor],
    labels: torch.Tensor,
    held: torch.Tensor,
    label: int,
    *,
    latent_dim: int,
    lengths: tuple[int, ...],
    fit_steps: int,
    options: dict[str, Any],
    points: int,
    max_windows: int | None = None,
) -> dict[int, dict[str, float]]:
    """One fold: fit, forecast the held-out trial's windows, measure its reconstructions."""
    hg = HGPDM(tr, labels, latent_dim, **options)
    gp = GPDM(tr, latent_dim, **options)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a step budget, as in the command (no fit converges)
        hg.fit(fit_steps)
        gp.fit(fit_steps)
    ridge, last = RidgeAR().fit(tr), LastFrameForecaster().fit(tr)
    ridge1 = RidgeAR().fit(tr, orders=(1,))
    vb_hg = VariationalInference(hg, measurement_points=points)
    vb_gp = VariationalInference(gp, measurement_points=points)
    frames = torch.cat(tr)
    pca = {f"PCA-{k} recon.": pca_reconstruction_rmse(frames, held, k) for k in PCA_DIMS}
    out = {}
    for T in lengths:
        z, nxt, _ = forecast_windows([held], [label], T, 2)
        z, nxt = z[:max_windows], nxt[:max_windows]
        kw = {"prune": None, "newton_steps": LAPLACE_STEPS}
        cf_hg = candidate_forecasts(vb_hg, z, **kw)
        cf_gp = candidate_forecasts(vb_gp, z, **kw)
        g_ml = cf_hg.result.g_ml
        hg_ar1 = cf_hg.pick(g_ml, ar1=True)
        recon = cf_hg.reconstruction[torch.arange(z.shape[0]), g_ml]  # [W, T + 1, Dz]
        seen = torch.cat([z, nxt[:, None]], 1)
        seen_res = vb_hg.infer(seen, **kw)
        recon_seen = vb_hg.predict_observations(seen, seen_res, joint=False)[0]
        ridge_pred = ridge.predict(z)
        preds = {
            "ridge AR": ridge_pred,
            "ridge AR order 1": ridge1.predict(z),
            "repeat last frame": last.predict(z),
            "H-GPDM VB": cf_hg.pick(g_ml),
            "H-GPDM VB + AR(1)": hg_ar1,
            "GPDM VB + AR(1)": cf_gp.pick(torch.zeros_like(g_ml), ar1=True),
            "H-GPDM + AR(1) / ridge mean": (hg_ar1 + ridge_pred) / 2,
        }
        row = {"windows": int(z.shape[0])}
        row |= {name: _rmse(p, nxt) for name, p in preds.items()}
        row["H-GPDM recon. z_T"] = _rmse(recon[:, -2], z[:, -1])
        row["H-GPDM recon. z_T+1 seen"] = _rmse(recon_seen[:, -1], nxt)
        out[T] = row | pca
    return out


def run(protocols: tuple[str, ...], *, quick: bool = False, dx3: bool = False) -> ResultTable:
    lengths = (5,) if quick else (5, 10)
    table = ResultTable(
        "Forecast and reconstruction RMSE of held-out walking trials (leave-one-trial-out, "
        "standardised channels)",
        list(COLUMNS),
        meta={**environment(), "quick": quick, "lengths": list(lengths), "seconds": {}},
    )
    for name in protocols:
        start = time.perf_counter()
        spec = PROTOCOLS[name]
        data = load_protocol(spec, "train", DATA)
        folds = spread_folds(loto_folds(data.labels)[0], data, 1 if quick else MAX_FOLDS[name])
        fit_steps = 10 if quick else DEFAULT_FIT_STEPS[name]
        dx = 3 if dx3 else DEFAULT_LATENT_DIM[name]
        rows: dict[int, list[dict[str, Any]]] = {T: [] for T in lengths}
        for train, held in folds:
            raw = [data.sequences[i] for i in train]
            std = Standardizer().fit(raw)
            scored = _score_fold(
                [std.transform(s) for s in raw],
                data.labels[train],
                std.transform(data.sequences[held[0]]),
                int(data.labels[held[0]]),
                latent_dim=dx,
                lengths=lengths,
                fit_steps=fit_steps,
                options=DEFAULT_OPTIONS[name],
                points=DEFAULT_MEASUREMENT_POINTS[name],
                max_windows=4 if quick else None,
            )
            for T in lengths:
                rows[T].append({"held out": data.trials[held[0]]} | scored[T])
        for T in lengths:
            for row in rows[T]:
                table.add(protocol=name, Dx=dx, T=T, **row)
            stats = {c: mean_sem([r[c] for r in rows[T]]) for c in (*FORECASTS, *RECONSTRUCTIONS)}
            windows = sum(r["windows"] for r in rows[T])
            for i, what in enumerate(("mean", "SEM")):
                values = {c: pair[i] for c, pair in stats.items()}
                table.add(
                    protocol=name, Dx=dx, T=T, windows=windows, **{"held out": what}, **values
                )
        table.meta["seconds"][name] = time.perf_counter() - start
    return table


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    arg = next((a.split("=", 1)[1] for a in argv if a.startswith("--protocols=")), None)
    protocols = tuple(arg.split(",")) if arg else (("walkers",) if quick else FORECAST_PROTOCOLS)
    unknown = [p for p in protocols if p not in FORECAST_PROTOCOLS]
    if unknown or not protocols:
        print(f"--protocols must list some of {FORECAST_PROTOCOLS}, got {arg!r}", file=sys.stderr)
        return 2
    if not DATA.is_dir():
        print(f"{DATA} not found: the CMU training trials are needed (see its README)")
        return 1
    dx3 = "--dx3" in argv
    table = run(protocols, quick=quick, dx3=dx3)
    print(table.to_markdown())
    suffix = ("_dx3" if dx3 else "") + ("_quick" if quick else "")
    table.to_json(RESULTS / f"forecast_anatomy{suffix}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
