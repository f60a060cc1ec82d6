"""Target prediction in table tennis (thesis Sec. 3.5, Fig. 3.7, Table 3.2).

A simulated opponent (:func:`hgpdm_torch.robots.table_tennis.opponent.sample_strokes`) returns
the ball to a target ``g`` (the ``x`` where the return crosses the robot's hitting plane); the
ball and racket are observed every 80 ms (Dz = 15). IDDMs are trained on 100 plays and predict
the target of 126 test plays 320, 240, 160 and 80 ms before the opponent hits the ball:

- the latent states are initialised by partial least squares
  (:func:`~hgpdm_torch.models.supervised_init`) rather than PCA: the target is carried by
  low-variance racket features (the racket normal and velocity), while PCA keeps the
  high-variance ball flight, which does not depend on the target;
  a PCA-initialised latent loses the target and the IDDM's error stays flat over the stroke;
- model selection over the measurement kernel (linear / RBF) and ``Dx = 3..6`` by k-fold
  cross-validation on the training plays (online IDDM, all horizons), with each
  configuration's test MAE (Table 3.2 layout);
- for the selected model: batch IDDM (Algorithm 3.1, window 4), online IDDM (Algorithm 3.2,
  ``eps = 0.2``), GP regression with ARD on a window chosen by validation, and the median
  (Fig. 3.7), plus ridge regression on a window (not in the thesis; a linear read-out of the
  raw observations) and a probabilistic movement primitive over the observations jointly with
  the target, conditioned on the observed prefix with its phase estimated
  (:class:`~hgpdm_torch.baselines.ProMPRegressor`, not in the thesis: the interaction-primitive
  baseline; its basis, phase grid and ridge chosen by the same ``cv_folds``-fold
  cross-validation of the training plays): MAE +- SEM in cm and the CPU time per observation;
- the linear-Gaussian intention-driven dynamics (:class:`~hgpdm_torch.models.LinearIDDM`, not in
  the thesis): a transition per frame index over the observations, its noise kind (full,
  diagonal, isotropic) and prior (coefficient precision, noise scale) chosen by the evidence of
  the training strokes; its beliefs at ``T = 1`` without forgetting (exact Bayes for the model)
  and at the evidence temperature and forgetting of 5-fold cross-validated beliefs of the
  training strokes (``temperature="cv", forgetting="cv"``), the latter also with the rank-1
  intention-state interaction (``interaction_rank=1``), and both of those with the noise kind
  and prior chosen by that cross-validation instead of the evidence (``select="cv"``), and the
  equal mixture of the beliefs of those two (:class:`~hgpdm_torch.inference.BeliefMixture`);
- the phase-aware IDDM (not in the thesis; :data:`PHASE_IDDM`: transitions that change along the
  stroke with a process noise per latent dim, its noise and g width chosen by the
  cross-validation of ``python -m benchmarks target_sweep --only=phase`` and
  ``--only="transition scales"``) with the selected kernel and Dx, online, and the equal
  mixture of its beliefs with those of the two linear IDDMs;
- how often the online belief's 90% credible set over the grid holds the grid value nearest to
  the true target (at the four horizons), at ``T = 1`` and with the evidence temperature fitted
  on the cross-validation folds' held-out beliefs (:func:`~hgpdm_torch.inference.fit_temperature`;
  a row of its own, posterior-mean MAE included).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import torch

from ..baselines import MedianPredictor, ProMPRegressor, WindowGPR, WindowRidge
from ..calibration import calibration, fit_temperature, grid_index
from ..crossval import contiguous_folds, held_out
from ..decision.beliefs import PHASE_IDDM
from ..inference.intention import (
    BeliefMixture,
    FilterBeliefs,
    OnlineIntentionFilter,
    infer_intention,
)
from ..models import IDDM, LinearIDDM, supervised_init
from ..progress import tqdm
from ..results import ResultTable
from ..validation import check_choice
from .arguments import output_file, random_seed, smoke_run

__all__ = [
    "HORIZONS_MS",
    "PHASE_IDDM",
    "THESIS_IDDM",
    "main",
    "target_prediction",
]

#: Prediction times before the opponent's hit [ms] and their observation indices (T = 6
#: observations, the last at the hit).
HORIZONS_MS = (320, 240, 160, 80)
_STEPS = (1, 2, 3, 4)


def _mae_sem(pred: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """MAE and its standard error, in cm. ``pred [n]``, ``truth [n]``."""
    err = 100.0 * (pred - truth).abs()
    return float(err.mean()), float(err.std() / len(err) ** 0.5)


#: the IDDM's kernel settings in this experiment (the thesis's kernel)
THESIS_IDDM: dict[str, Any] = {"alpha": (0.9, 0.3, 0.1, 1e-2), "alpha_g": (4.0, 0.1)}


def _fit_iddm(
    obs, targets, kernel: str, dx: int, steps: int, seed: int, init: str = "pls", **options
) -> IDDM:
    """The IDDM on the plays ``obs [n, T, Dz]`` with their ``targets``: :data:`THESIS_IDDM`'s
    settings, overridden by ``options`` (e.g. :data:`PHASE_IDDM`)."""
    torch.manual_seed(seed)
    x0 = supervised_init(obs, targets, dx) if init == "pls" else "pca"
    model = IDDM(
        list(obs), targets, dx, intention="continuous", measurement=kernel, init=x0,
        **(THESIS_IDDM | options),
    )  # fmt: skip
    model.fit(steps)  # its FitResult stays on the model (model.fit_result)
    return model


def _online(
    model,
    obs,
    grid,
    forgetting: float,
    inducing: int | None = None,
    temperature: float = 1.0,
) -> tuple[torch.Tensor, float, torch.Tensor]:
    """Posterior-mean target after each observation ``[n, T]``, CPU ms per observation and
    the log beliefs over the grid ``[n, T, K]``."""
    f = OnlineIntentionFilter(
        model,
        grid,
        forgetting=forgetting,
        batch_size=obs.shape[0],
        inducing=inducing,
        temperature=temperature,
    )
    means, logs = [], []
    start = time.process_time()
    for t in range(obs.shape[1]):
        belief = f.update(obs[:, t])
        means.append(belief.mean[:, 0])
        logs.append(belief.log_prob)
    ms = 1e3 * (time.process_time() - start) / obs.numel() * obs.shape[-1]
    return torch.stack(means, 1), ms, torch.stack(logs, 1)


def _cv_mae(
    obs, y, splits, kernel, dx, steps, seed, init, grid, forgetting, **options
) -> tuple[float, torch.Tensor, torch.Tensor]:
    """Cross-validated online-IDDM MAE [cm] over the four horizons, pooled over the held-out plays
    of all folds (``splits``: :func:`~hgpdm_torch.crossval.contiguous_folds` of the training
    plays): every training play is validated once, at every horizon (the 80 ms error of a single
    25% split of 100 plays left the selection to noise, SEM ~ 6 cm). Also returns the held-out
    log beliefs ``[n, 4, K]`` at the horizons and the grid index of each play's target ``[n,
    4]`` (to calibrate the selected model's evidence temperature). ``options``: the IDDM's, as
    :func:`_fit_iddm` takes them (e.g. :data:`PHASE_IDDM`)."""

    def fold(k: int, train: list[int], held: list[int]) -> tuple[torch.Tensor, ...]:
        model = _fit_iddm(obs[train], y[train], kernel, dx, steps, seed, init, **options)
        mean, _, log_prob = _online(model, obs[held][:, : _STEPS[-1] + 1], grid, forgetting)
        truth = grid_index(y[held], grid)[:, None].expand(-1, len(_STEPS))
        return (
            100.0 * (mean[:, list(_STEPS)] - y[held, None]).abs(),
            log_prob[:, list(_STEPS)],
            truth,
        )

    errors, logs, truths = zip(*held_out(splits, fold), strict=True)
    return float(torch.cat(errors).mean()), torch.cat(logs), torch.cat(truths)


def _linear_iddm(
    obs, y, grid, obs_test, y_test, **options
) -> tuple[dict[str, Any], list, float, LinearIDDM]:
    """:class:`LinearIDDM` with its noise kind and prior chosen (``"auto"``) by the evidence of
    the training strokes or the given ``select`` and the given ``temperature``/``forgetting``
    options; returns the choices with
    the test beliefs' calibration, the test scores, the CPU ms per observation and the model."""
    model = LinearIDDM(**options).fit(obs, y)
    start = time.process_time()
    belief = model.beliefs(obs_test, grid)
    ms = 1e3 * (time.process_time() - start) / (obs_test.shape[0] * obs_test.shape[1])
    truth = grid_index(y_test, grid)[:, None].expand(-1, len(_STEPS))
    choice = {"noise": model.noise_kind, "coef_precision": model.prior[0],
              "noise_prior": model.prior[1],
              "log_evidence": model.log_marginal_likelihood(), "temperature": model.temperature,
              "forgetting": model.forgetting, "interaction_rank": model.interaction_rank,
              "calibration": calibration(belief.prob[:, list(_STEPS)], truth)}  # fmt: skip
    mean = belief.mean[..., 0]
    return choice, [_mae_sem(mean[:, s], y_test) for s in _STEPS], ms, model


def target_prediction(
    *,
    n_train: int = 100,
    n_test: int = 126,
    kernels: tuple[str, ...] = ("linear", "rbf"),
    latent_dims: tuple[int, ...] = (3, 4, 5, 6),
    grid_size: int = 25,
    window: int = 4,
    forgetting: float = 0.2,
    fit_steps: int = 40,
    inducing: tuple[int, ...] = (250, 125),
    init: str = "pls",
    cv_folds: int = 3,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Run the experiment; returns a :class:`ResultTable`.

    Rows ``selection``: one per (kernel, Dx) with the ``cv_folds``-fold cross-validated MAE on
    the training plays over all horizons (online IDDM) and
    the test MAE at every horizon (Table 3.2 reads the 80 ms column). Rows ``comparison``: the
    selected model's batch and online IDDM (also with a sparse transition GP on each number of
    pseudo-inputs in ``inducing``, Sec. 3.3.3), GPR, ridge, the ProMP and the median (Fig.
    3.7). MAE +- SEM in cm; ``meta`` holds the raw numbers, the targets' spread and the
    selected configuration.
    ``init`` is the latent initialisation: ``"pls"``
    (:func:`~hgpdm_torch.models.supervised_init`) or ``"pca"``.
    """
    check_choice(init, "init", ("pls", "pca"))
    if not isinstance(cv_folds, int) or not 2 <= cv_folds <= n_train // 2:
        raise ValueError(f"cv_folds must be an int in [2, n_train / 2], got {cv_folds!r}")
    from ..robots.table_tennis.opponent import sample_strokes

    gen = torch.Generator().manual_seed(seed)
    strokes = sample_strokes(n_train + n_test, generator=gen, progress=progress)
    obs, y = strokes.obs, strokes.targets
    train, test = slice(0, n_train), slice(n_train, n_train + n_test)
    folds = contiguous_folds(n_train, cv_folds)
    lim = float(strokes_limit(y[train]))  # training targets only (the test ones are unseen)
    grid = torch.linspace(-lim, lim, grid_size)
    obs_test, y_test = obs[test][:, : _STEPS[-1] + 1], y[test]
    table = ResultTable(
        "Table 3.2 / Fig. 3.7: table-tennis target prediction, MAE +- SEM [cm]",
        ["part", "method", "kernel", "Dx", "CV MAE", *(f"{h} ms" for h in HORIZONS_MS),
         "90% set coverage [%]", "CPU ms/obs"],  # fmt: skip
        meta={"seed": seed, "init": init, "n_train": n_train, "n_test": n_test, "target_std_cm":
              100 * float(y_test.std()), "grid": [-lim, lim, grid_size], "mae": {}},
    )  # fmt: skip
    configs = [(k, d) for k in kernels for d in latent_dims]
    best, best_val = None, float("inf")
    for kernel, dx in tqdm(configs, disable=not progress, desc="model selection"):
        val_mae, val_logs, val_truth = _cv_mae(
            obs[train], y[train], folds, kernel, dx, fit_steps, seed, init, grid, forgetting
        )
        model = _fit_iddm(obs[train], y[train], kernel, dx, fit_steps, seed, init)
        mean, ms, log_prob = _online(model, obs_test, grid, forgetting)
        scores = [_mae_sem(mean[:, s], y_test) for s in _STEPS]
        table.meta["mae"][f"online {kernel} Dx={dx}"] = scores
        table.add(**_row("selection", "IDDM online", kernel, dx, val_mae, scores, ms))
        if val_mae < best_val:
            best, best_val, best_model = (kernel, dx), val_mae, model
            best_online, best_val_logs = (mean, ms, log_prob), (val_logs, val_truth)
    table.meta["selected"] = {"kernel": best[0], "Dx": best[1]}
    table.meta["fit"] = best_model.fit_result.summary()
    # the same filter on the selected model's own training plays: the gap to the test MAE is
    # how much of the dynamics' dependence on g is memorised rather than generalised
    own, _, _ = _online(best_model, obs[train][:, : _STEPS[-1] + 1], grid, forgetting)
    table.meta["train_mae_online"] = [_mae_sem(own[:, s], y[train]) for s in _STEPS]
    # 90% credible sets over the grid on the test plays, at T = 1 and at the evidence
    # temperature fitted on the held-out beliefs of the cross-validation folds
    temperature = fit_temperature(*best_val_logs)
    truth = grid_index(y_test, grid)[:, None].expand(-1, len(_STEPS))
    mean, ms, log_prob = best_online
    cal = calibration(log_prob[:, list(_STEPS)].exp(), truth)
    scores = [_mae_sem(mean[:, s], y_test) for s in _STEPS]
    table.add(
        **_row("comparison", f"IDDM online eps={forgetting}", *best, None, scores, ms),
        **{"90% set coverage [%]": round(100 * cal["coverage"], 1)},
    )
    mean_t, ms_t, log_t = _online(best_model, obs_test, grid, forgetting, temperature=temperature)
    cal_t = calibration(log_t[:, list(_STEPS)].exp(), truth)
    scores_t = [_mae_sem(mean_t[:, s], y_test) for s in _STEPS]
    table.meta["mae"]["online calibrated"] = scores_t
    table.meta["temperature"] = temperature
    table.meta["calibration"] = {"T=1": cal, "fitted T": cal_t}
    name = f"IDDM online eps={forgetting}, T={temperature:.3g} (CV)"
    table.add(
        **_row("comparison", name, *best, None, scores_t, ms_t),
        **{"90% set coverage [%]": round(100 * cal_t["coverage"], 1)},
    )
    for m in inducing:
        sparse, ms_sparse, _ = _online(best_model, obs_test, grid, forgetting, inducing=m)
        scores_sparse = [_mae_sem(sparse[:, s], y_test) for s in _STEPS]
        table.meta["mae"][f"online sparse M={m}"] = scores_sparse
        name = f"IDDM online eps={forgetting}, sparse M={m}"
        table.add(**_row("comparison", name, *best, None, scores_sparse, ms_sparse))
    calibrate = {"temperature": "cv", "forgetting": "cv"}
    linear_models = {}
    for key, options in (
        ("linear iddm", {}),
        ("linear iddm calibrated", calibrate),
        ("linear iddm interaction calibrated", {"interaction_rank": 1, **calibrate}),
        ("linear iddm selected", {"select": "cv", **calibrate}),
        ("linear iddm interaction selected", {"interaction_rank": 1, "select": "cv", **calibrate}),
    ):
        choice, scores, ms, model = _linear_iddm(
            obs[train], y[train], grid, obs_test, y_test, **options
        )
        linear_models[key] = model
        table.meta[key.replace(" ", "_")] = choice
        table.meta["mae"][key] = scores
        prior = (f"{choice['noise']} noise, lambda={choice['coef_precision']:.3g}, "
                 f"psi={choice['noise_prior']:.3g}, T={choice['temperature']:.3g}, "
                 f"eps={choice['forgetting']:.3g}"
                 + (f", interaction rank {choice['interaction_rank']}"
                    if choice["interaction_rank"] else ""))  # fmt: skip
        chosen = "all by CV" if "select" in options else "T, eps by CV" if options else ""
        name = f"linear IDDM per phase ({prior}{f' ({chosen})' if chosen else ''})"
        table.add(
            **_row("comparison", name, None, None, None, scores, ms),
            **{"90% set coverage [%]": round(100 * choice["calibration"]["coverage"], 1)},
        )
    # the equal mixture of the two selected models' beliefs
    mixture = BeliefMixture([linear_models["linear iddm selected"],
                             linear_models["linear iddm interaction selected"]])  # fmt: skip
    start = time.process_time()
    belief = mixture.beliefs(obs_test, grid)
    ms = 1e3 * (time.process_time() - start) / (obs_test.shape[0] * obs_test.shape[1])
    truth = grid_index(y_test, grid)[:, None].expand(-1, len(_STEPS))
    cal_mix = calibration(belief.prob[:, list(_STEPS)], truth)
    scores = [_mae_sem(belief.mean[:, s, 0], y_test) for s in _STEPS]
    table.meta["mae"]["linear iddm mixture"] = scores
    table.meta["linear_iddm_mixture"] = {"calibration": cal_mix}
    name = "BeliefMixture of the two linear IDDMs all by CV (equal weights)"
    table.add(
        **_row("comparison", name, None, None, None, scores, ms),
        **{"90% set coverage [%]": round(100 * cal_mix["coverage"], 1)},
    )
    # the phase-aware IDDM (PHASE_IDDM) with the selected kernel and Dx, and its beliefs in an
    # equal mixture with the two linear IDDMs
    phased = _fit_iddm(obs[train], y[train], *best, fit_steps, seed, init, **PHASE_IDDM)
    table.meta["phase_iddm"] = {"options": {k: str(v) for k, v in PHASE_IDDM.items()},
                                "fit": phased.fit_result.summary()}  # fmt: skip
    member = FilterBeliefs(phased, forgetting=forgetting)
    start = time.process_time()
    belief = member.beliefs(obs_test, grid)
    ms = 1e3 * (time.process_time() - start) / (obs_test.shape[0] * obs_test.shape[1])
    for key, name, b in (
        ("phase iddm", f"IDDM online eps={forgetting}, per phase, transition scales (phase "
         "width, noise, g width by CV)", belief),
        ("phase iddm + linear mixture", "BeliefMixture of the per-phase IDDM and the two linear "
         "IDDMs (equal weights)", BeliefMixture([member, *mixture.models]).beliefs(obs_test, grid)),
    ):  # fmt: skip
        cal_b = calibration(b.prob[:, list(_STEPS)], truth)
        scores = [_mae_sem(b.mean[:, s, 0], y_test) for s in _STEPS]
        table.meta["mae"][key] = scores
        table.add(
            **_row("comparison", name, *best, None, scores, ms if key == "phase iddm" else None),
            **{"90% set coverage [%]": round(100 * cal_b["coverage"], 1)},
        )
    start = time.process_time()
    batch = infer_intention(best_model, obs_test, grid, window=window).mean[..., 0]
    ms = 1e3 * (time.process_time() - start) / (obs_test.shape[0] * obs_test.shape[1])
    scores = [_mae_sem(batch[:, s], y_test) for s in _STEPS]
    table.meta["mae"]["batch"] = scores
    table.add(**_row("comparison", f"IDDM batch window {window}", *best, None, scores, ms))
    for key, label, baseline in (
        ("gpr", "GPR (ARD, window {})", WindowGPR(windows=(1, 2, 3), seed=seed)),
        ("ridge", "ridge (window {})", WindowRidge(windows=(1, 2, 3), seed=seed)),
        ("promp", "ProMP ({} basis, phase {})", ProMPRegressor(folds=cv_folds, seed=seed)),
    ):
        baseline.fit(list(obs[train]), y[train])
        start = time.process_time()
        pred = baseline.predict(obs_test)
        pred = pred[0] if isinstance(pred, tuple) else pred  # GPR also returns its std
        ms = 1e3 * (time.process_time() - start) / (obs_test.shape[0] * obs_test.shape[1])
        scores = [_mae_sem(pred[:, s], y_test) for s in _STEPS]
        table.meta["mae"][key] = scores
        if isinstance(baseline, ProMPRegressor):  # options chosen by cross-validation
            table.meta["promp_options"] = {k: str(v) for k, v in baseline.options.items()}
            speeds = baseline.options["speeds"]
            name = label.format(
                baseline.options["num_basis"], "estimated" if len(speeds) > 1 else "known"
            )
        else:
            table.meta[f"{key}_window"] = baseline.window
            name = label.format(baseline.window)
        table.add(**_row("comparison", name, None, None, None, scores, ms))
    med = MedianPredictor().fit(None, y[train]).predict(obs_test)
    scores = [_mae_sem(med[:, s], y_test) for s in _STEPS]
    table.meta["mae"]["median"] = scores
    table.add(**_row("comparison", "median", None, None, None, scores, None))
    table.meta["mae"]["online"] = [_mae_sem(mean[:, s], y_test) for s in _STEPS]
    return table


def strokes_limit(targets: torch.Tensor) -> float:
    """Half-width of the intention grid: the largest training target, rounded up to 10 cm."""
    return float(torch.ceil(targets.abs().max() * 10) / 10)


def _row(part, method, kernel, dx, val, scores, ms) -> dict[str, Any]:
    row: dict[str, Any] = {"part": part, "method": method, "kernel": kernel, "Dx": dx}
    if val is not None:
        row["CV MAE"] = round(val, 1)
    for h, (m, s) in zip(HORIZONS_MS, scores, strict=True):
        row[f"{h} ms"] = f"{m:.1f} +- {s:.1f}"
    if ms is not None:
        row["CPU ms/obs"] = round(ms, 2)
    return row


def main(argv: list[str]) -> int:
    """``hgpdm target-prediction [--quick] [--out results.json] [--seed N] [--init pls|pca]``."""
    parser = argparse.ArgumentParser(prog="hgpdm target-prediction", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small smoke-test sizes")
    parser.add_argument("--out", type=output_file, help="write the table as JSON")
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--init", choices=("pls", "pca"), default="pls", help="latent init")
    args = parser.parse_args(argv)
    quick = args.quick or smoke_run()
    kwargs = (
        {
            "n_train": 24,
            "n_test": 16,
            "kernels": ("linear",),
            "latent_dims": (3, 4),
            "grid_size": 13,
            "fit_steps": 10,
        }  # fmt: skip
        if quick
        else {}
    )
    table = target_prediction(seed=args.seed, init=args.init, progress=not quick, **kwargs)
    print(table.to_markdown())
    if args.out:
        table.to_json(args.out)
    return 0
