"""Next-pose prediction on the thesis's CMU protocols (Sec. 2.4.1, Tables 2.1-2.4).

Protocols (:data:`~hgpdm_torch.datasets.cmu.PROTOCOLS`): ``walkers`` (g = subject 07, 08, 16,
35) and ``weird-walking`` (g = one of subject 132's four styles), both down-sampled by ten
(12 frames/s), Taylor-style features (:func:`~hgpdm_torch.datasets.walkers.motion_features`),
channels constant in training dropped and the rest standardised with training statistics only.

Two evaluations:

- **leave-one-trial-out cross-validation** within the training trials (the default, and how the
  options are chosen): each trial whose label has another training trial is held out in turn,
  the models are fitted on the rest; a trial that is its label's only one is listed as not
  testable (the models could not know its label);
- **test trials** (``test_folder``): the models are fitted once on all training trials and score
  the protocol's test trials found there (those absent are listed; none is taken from the
  training folder).

Before any work a run checks which trials are there
(:func:`~hgpdm_torch.datasets.walkers.protocol_trials`): the command says what it found per
label and stops, naming the missing files, when a label has no training trial or the test
folder no test trial.

Every held-out trial is cut into windows of T frames (every ``stride`` frames) and each method
forecasts the next frame. The GP models observe what the protocol's CV chose
(:data:`DEFAULT_FEATURES`, :func:`~hgpdm_torch.datasets.walkers.frame_features`: the frames, or
each frame beside its change or beside the previous frame, in training and in the windows) and
forecast the frame part; the baselines always see the frames. From one VB posterior per
window over all g (every candidate refined):

- ``VB H-GPDM``: the ML g's forecast (Algorithm 2.2, the thesis's column), its recognition
  accuracy and the 90%-set coverage of the posterior over g; beside it, ``ProMP accuracy``: the
  label whose ProMP (:class:`~hgpdm_torch.baselines.ProMPClassifier`, one per label over the
  training trials' windows, options by class-stratified CV over those windows) gives the window
  the highest likelihood;
- ``VB H-GPDM (BMA)``: the forecasts of all g averaged under the posterior over g;
- ``oracle VB``: the true g's forecast; with ``+ AR(1) residual``: the window's deviation from
  the model's reconstruction carried on as an AR(1) process (not in the thesis);

``GPDM VB``, the MAP baseline (conditional GPDM) ``oracle MAP`` / ``GPDM MAP`` at the same
inference's Laplace start (Levenberg-Marquardt to the MAP states, :data:`LAPLACE_STEPS`
iterations), and the baselines: repeat the last frame,
ridge AR (order and penalty by CV grouped by trial) and a GRU (hidden size and epochs by
grouped CV). RMSE is over all standardised channels of a trial's windows; the
``average`` row is the mean over trials (with its standard error), as the thesis's tables.
``HGPDM_SMOKE=1`` shrinks the run.
"""

from __future__ import annotations

import argparse
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any, Literal

import torch

from ..baselines import GRUForecaster, LastFrameForecaster, ProMPClassifier, RidgeAR
from ..calibration import calibration
from ..crossval import held_out
from ..datasets.cmu import PROTOCOLS, Protocol, load_protocol, load_trials
from ..datasets.walkers import (
    FRAME_FEATURES,
    MissingTrialsError,
    Standardizer,
    frame_features,
    loto_folds,
    protocol_trials,
    spread_folds,
)
from ..inference.variational import VariationalInference
from ..inference.variational.prediction import candidate_forecasts
from ..models import GPDM, HGPDM
from ..parallel import Executor
from ..results import ResultTable
from .arguments import (
    SMOKE,
    add_executor_arguments,
    connect,
    int_at_least,
    output_file,
    positive_int,
)
from .intervals import mean_sem
from .style_recognition import chunked_windows, forecast_windows, window_entries
from .walkers_compare import compare_runs

__all__ = [
    "DEFAULT_FEATURES",
    "DEFAULT_FIT_STEPS",
    "DEFAULT_LATENT_DIM",
    "DEFAULT_MEASUREMENT_POINTS",
    "DEFAULT_OPTIONS",
    "FALLBACK_FEATURES",
    "FALLBACK_FIT_STEPS",
    "FALLBACK_LATENT_DIM",
    "FALLBACK_MEASUREMENT_POINTS",
    "FORECAST_PROTOCOLS",
    "METHODS",
    "MODEL_METHODS",
    "compare_runs",
    "main",
    "report",
    "walkers",
]

FORECAST_PROTOCOLS = ("walkers", "weird-walking")
#: the models' rows, shared with gap recovery (:mod:`~hgpdm_torch.experiments.gap_recovery`)
MODEL_METHODS = ("VB H-GPDM", "VB H-GPDM (BMA)", "oracle VB", "oracle MAP", "GPDM VB", "GPDM MAP")
METHODS = (
    *MODEL_METHODS,
    "VB H-GPDM + AR(1) residual",
    "VB H-GPDM (BMA) + AR(1) residual",
    "oracle VB + AR(1) residual",
    "GPDM VB + AR(1) residual",
    "repeat last frame",
    "ridge AR (CV)",
    "GRU (CV)",
)
#: per protocol, the model options leave-one-trial-out CV chose on its own training trials (the
#: mean RMSE of the VB H-GPDM + AR(1) residual forecast at T = 5 and 10; docs page "Walking
#: motion capture"). Walkers: the measurement GP's RBF width stays at its initial value (learned,
#: it collapses onto the training frames); Weird Walking: the width is learned (kept, the
#: H-GPDM's forecast errs about twice as much, worse on each held-out style). A protocol of
#: one's own gets the models' own defaults.
DEFAULT_OPTIONS: dict[str, dict[str, Any]] = {
    "walkers": {"learn_measurement_width": False},
    "weird-walking": {"learn_measurement_width": True},
}
#: per protocol, VB and MAP inference route the measurement GP through at most this many
#: pseudo-inputs (the DTC sparse GP). Walkers: 500, above every fold's frame count (N <= 307), so
#: the GP is exact. Weird Walking (~1,300 training frames): 150, the choice of the same
#: leave-one-trial-out CV with the learned width (against 500: the H-GPDM + AR(1) forecast and
#: the ratio to the GPDM better, recognition 82% / 74% against 72% / 69%, forecasts about twice
#: as fast; docs page "Walking motion capture"). A protocol of one's own: 500.
DEFAULT_MEASUREMENT_POINTS: dict[str, int] = {"walkers": 500, "weird-walking": 150}
#: the pseudo-input count of a protocol without its own CV choice
FALLBACK_MEASUREMENT_POINTS = 500
#: per protocol, the MAP steps per fit that the same cross-validation chose: Walkers 300 (the
#: thesis's; 150 and 600 did worse), Weird Walking 150 (with its learned width and 150
#: pseudo-inputs: the H-GPDM + AR(1) forecast 0.423 / 0.438 against 0.434 / 0.440 with 300,
#: recognition 81% / 88% against 82% / 74%, and the fits take half the time). Others: 300.
DEFAULT_FIT_STEPS: dict[str, int] = {"walkers": 300, "weird-walking": 150}
FALLBACK_FIT_STEPS = 300
#: per protocol, the latent dimension Dx of both models that the same cross-validation chose:
#: Walkers 3 (the thesis's; 2, 4, 5 and 10 forecast worse), Weird Walking 10 (with its other
#: defaults the H-GPDM + AR(1) forecast 0.369 on average over T = 5 and 10, against 0.418 with
#: Dx = 3, 0.395 with 6, 0.379 with 15 and 0.377 with 20; its poses need more than three
#: dimensions: held-out frames lie 0.8 sd from the best 3-D linear subspace of the training
#: frames). Others: 3, the thesis's.
DEFAULT_LATENT_DIM: dict[str, int] = {"walkers": 3, "weird-walking": 10}
FALLBACK_LATENT_DIM = 3
#: per protocol, what both models observe of the frames
#: (:func:`~hgpdm_torch.datasets.walkers.frame_features`), the same cross-validation's choice.
#: Walkers: ``"velocity"``, each frame beside its change (the H-GPDM + AR(1) residual forecast
#: 0.318 / 0.291 at T = 5 / 10 against 0.325 / 0.301 with the frames alone and 0.322 / 0.297
#: beside the previous frame, and ahead of ridge AR, the GRU and the last frame on every subject;
#: 07, where one walk trains per fold, gains most: 0.460 / 0.422 against 0.519 / 0.471).
#: Weird Walking: ``"lagged"``, each frame beside the previous frame (0.354 / 0.366 against
#: 0.371 / 0.367 with the frames alone, recognition 84% / 91%; the ratio to the GPDM VB is
#: 0.77 / 0.63 against 0.75 / 0.55, as the GPDM gains more; beside the change it loses, 0.48 /
#: 0.49, recognition 70%).
#: Others: ``"frames"``, the thesis's.
DEFAULT_FEATURES: dict[str, str] = {"walkers": "velocity", "weird-walking": "lagged"}
FALLBACK_FEATURES = "frames"


# Levenberg-Marquardt iterations of the Laplace start, VB's default, which also give the MAP rows
# (MAPInference runs 50 by default: on 40 in-sample Weird Walking windows of T = 10, `python -m
# benchmarks map_solver`, its forecasts at 30 iterations erred 0.476 / 0.393 (oracle H-GPDM /
# GPDM) against 0.477 / 0.419 at 50, in three quarters of the time)
LAPLACE_STEPS = 30


def _rmse(pred: torch.Tensor, truth: torch.Tensor) -> float:
    return float((pred - truth).pow(2).mean().sqrt())


def _vb_forecasts(
    vb: VariationalInference, z: torch.Tensor, y: torch.Tensor
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """The VB and MAP rows of one model from one inference per window (see the module
    docstring): the Laplace start (Levenberg-Marquardt from the MAP baseline's initial states,
    without pruning) gives the MAP baseline's states.

    Returns:
        forecasts by method suffix, the ML g ``[W]`` (index into ``vb.values``, which is the
        code) and the posterior over g ``[W, K]``.
    """
    K = int(vb.values.numel()) if vb.kind == "discrete" else 1

    def rows(w: torch.Tensor, truth: torch.Tensor) -> tuple[dict[str, torch.Tensor], Any]:
        cf = candidate_forecasts(vb, w, prune=None, newton_steps=LAPLACE_STEPS)
        ml = cf.result.g_ml
        out = {"": cf.pick(ml), " + AR(1) residual": cf.pick(ml, ar1=True)}
        if K > 1:  # a candidate's index is its code (``values`` is ``arange(K)``)
            out |= {
                " (BMA)": cf.averaged(),
                " (BMA) + AR(1) residual": cf.averaged(ar1=True),
                " oracle": cf.pick(truth),
                " oracle + AR(1) residual": cf.pick(truth, ar1=True),
                " oracle MAP": cf.pick(truth, map_states=True),
            }
        else:
            out[" MAP"] = cf.pick(torch.zeros_like(ml), map_states=True)
        return out, cf.result

    parts = chunked_windows(rows, z, window_entries(vb, K, z.shape[1]), truth=y)
    forecasts = {key: torch.cat([p[0][key] for p in parts]) for key in parts[0][0]}
    g_ml = torch.cat([p[1].g_ml for p in parts])
    return forecasts, g_ml, torch.cat([p[1].posterior for p in parts])


def _score_split(
    train: list[torch.Tensor],
    train_labels: torch.Tensor,
    test: list[torch.Tensor],
    test_labels: torch.Tensor,
    *,
    lengths: tuple[int, ...],
    stride: int,
    latent_dim: int,
    fit_steps: int,
    options: dict[str, Any],
    sharing: float,
    noise_per_label: bool,
    measurement_points: int | None,
    features: str,
) -> tuple[dict[int, list[dict[str, Any]]], dict[str, Any]]:
    """Fit every model on ``train`` (raw features) and score each ``test`` trial. The GP models
    observe :func:`~hgpdm_torch.datasets.walkers.frame_features` ``(., features)`` of the
    standardised frames (windows too) and forecast the frame part; the baselines see the frames.

    Returns:
        per window length, one row per test trial (``windows``, every method's RMSE,
        ``accuracy``, ``coverage``), and the fits' summaries.
    """
    short = [j for j, s in enumerate(test) if s.shape[0] <= max(lengths)]
    if short:
        raise ValueError(
            f"test trials {short} have at most max(lengths) = {max(lengths)} frames: no window "
            f"to forecast from; shorten the windows or leave those trials out"
        )
    std = Standardizer().fit(train)
    tr = [std.transform(s) for s in train]
    te = [std.transform(s) for s in test]
    start = time.perf_counter()
    observed = [frame_features(s, features) for s in tr]
    hg = HGPDM(
        observed,
        train_labels,
        latent_dim,
        sharing=sharing,
        noise_per_value=noise_per_label,
        **options,
    )
    gp = GPDM(observed, latent_dim, **options)
    fits: dict[str, Any] = {
        name: m.fit(fit_steps).summary() for name, m in (("H-GPDM", hg), ("GPDM", gp))
    }
    fits["seconds"] = time.perf_counter() - start
    if noise_per_label:
        fits["H-GPDM"]["alpha_4 per label"] = hg.value_noise.tolist()
    last, ridge = LastFrameForecaster().fit(tr), RidgeAR().fit(tr)
    fits["ridge_order"] = ridge.order_
    sparse = {"measurement_points": measurement_points}
    vb_hg, vb_gp = VariationalInference(hg, **sparse), VariationalInference(gp, **sparse)
    rows: dict[int, list[dict[str, Any]]] = {}
    for T in lengths:
        gru = GRUForecaster().fit(tr, T)
        fits[f"gru T={T}"] = {"hidden": gru.hidden_, "epochs": gru.epochs_}
        # one ProMP per label over the training trials' windows: the window's likelihood
        z_tr, _, y_tr = forecast_windows(tr, train_labels, T, stride)
        promp = ProMPClassifier(online=False).fit(list(z_tr), y_tr)
        fits[f"promp T={T}"] = {k: str(v) for k, v in promp.options.items()}
        start = time.perf_counter()
        z, nxt, y = forecast_windows(te, test_labels, T, stride)
        trial = torch.cat(
            [torch.full((len(range(0, s.shape[0] - T, stride)),), j) for j, s in enumerate(te)]
        )
        seen = frame_features(z, features)
        hg_rows, g_ml, post = _vb_forecasts(vb_hg, seen, y)
        gp_rows, _, _ = _vb_forecasts(vb_gp, seen, y)
        frames = z.shape[-1]  # the forecast frame: the first channels of the features
        hg_rows = {k: v[..., :frames] for k, v in hg_rows.items()}
        gp_rows = {k: v[..., :frames] for k, v in gp_rows.items()}
        preds = {
            "VB H-GPDM": hg_rows[""],
            "VB H-GPDM (BMA)": hg_rows[" (BMA)"],
            "oracle VB": hg_rows[" oracle"],
            "oracle MAP": hg_rows[" oracle MAP"],
            "GPDM VB": gp_rows[""],
            "GPDM MAP": gp_rows[" MAP"],
            "VB H-GPDM + AR(1) residual": hg_rows[" + AR(1) residual"],
            "VB H-GPDM (BMA) + AR(1) residual": hg_rows[" (BMA) + AR(1) residual"],
            "oracle VB + AR(1) residual": hg_rows[" oracle + AR(1) residual"],
            "GPDM VB + AR(1) residual": gp_rows[" + AR(1) residual"],
            "repeat last frame": last.predict(z),
            "ridge AR (CV)": ridge.predict(z),
            "GRU (CV)": gru.predict(z),
        }
        rows[T] = []
        for j in range(len(te)):
            keep = trial == j
            row: dict[str, Any] = {"windows": int(keep.sum())}
            row |= {name: _rmse(p[keep], nxt[keep]) for name, p in preds.items()}
            row["accuracy"] = float((g_ml[keep] == y[keep]).double().mean())
            promp_ml = promp.window_log_proba(z[keep]).argmax(-1)
            row["ProMP accuracy"] = float((promp_ml == y[keep]).double().mean())
            row["coverage"] = calibration(post[keep], y[keep])["coverage"]
            rows[T].append(row)
        fits[f"forecast seconds T={T}"] = time.perf_counter() - start
    return rows, fits


def _protocol_choice(name: str, protocol: str, value: object) -> Any:
    """The value of the setting ``name`` (``"measurement_points"``, ``"fit_steps"``,
    ``"latent_dim"`` or ``"features"``) to run: ``value``, or for ``"protocol"`` the protocol's
    CV choice (:data:`DEFAULT_MEASUREMENT_POINTS` / :data:`DEFAULT_FIT_STEPS` /
    :data:`DEFAULT_LATENT_DIM` / :data:`DEFAULT_FEATURES`, else the fallback). ``None`` (the
    exact GP) only for ``measurement_points``; ``features`` is one of
    :data:`~hgpdm_torch.datasets.walkers.FRAME_FEATURES`."""
    defaults, fallback = {
        "measurement_points": (DEFAULT_MEASUREMENT_POINTS, FALLBACK_MEASUREMENT_POINTS),
        "fit_steps": (DEFAULT_FIT_STEPS, FALLBACK_FIT_STEPS),
        "latent_dim": (DEFAULT_LATENT_DIM, FALLBACK_LATENT_DIM),
        "features": (DEFAULT_FEATURES, FALLBACK_FEATURES),
    }[name]
    if isinstance(value, str) and value == "protocol":
        return defaults.get(protocol, fallback)
    if name == "features":
        if value not in FRAME_FEATURES:
            raise ValueError(
                f"features must be one of {FRAME_FEATURES} or 'protocol', got {value!r}"
            )
        return value
    exact = name == "measurement_points" and value is None
    if not exact and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        also = ", None (the exact GP)" if name == "measurement_points" else ""
        raise ValueError(f"{name} must be a positive int{also} or 'protocol', got {value!r}")
    return value


def walkers(
    protocol: str | Protocol = "walkers",
    *,
    folder: str | Path = "../shared/data/cmu",
    test_folder: str | Path | None = None,
    lengths: tuple[int, ...] = (5, 10),
    latent_dim: int | Literal["protocol"] = "protocol",
    fit_steps: int | Literal["protocol"] = "protocol",
    stride: int = 2,
    model_options: dict[str, Any] | None = None,
    sharing: float = 0.0,
    noise_per_label: bool = False,
    measurement_points: int | None | Literal["protocol"] = "protocol",
    features: str = "protocol",
    max_folds: int | None = None,
    executor: Executor | None = None,
    progress: bool = False,
) -> ResultTable:
    """Tables 2.1-2.4 on a CMU protocol, with baselines (see the module docstring).

    Args:
        protocol: ``"walkers"``, ``"weird-walking"`` or a :class:`~hgpdm_torch.datasets.cmu.
            Protocol` of one's own.
        folder: the training trials' folder.
        test_folder: score the protocol's test trials found there, and only there (their
            skeletons may come from ``folder``; models fitted on all training trials);
            ``None``: leave-one-trial-out CV within the training trials.
        lengths: window lengths T.
        latent_dim: Dx of both models; ``"protocol"`` (default): the protocol's CV choice,
            :data:`DEFAULT_LATENT_DIM` (3 on Walkers, 10 on Weird Walking; 3 for a protocol of
            one's own).
        fit_steps: maximum MAP steps per fit; ``"protocol"`` (default): the protocol's CV
            choice, :data:`DEFAULT_FIT_STEPS` (300 on Walkers, 150 on Weird Walking; 300 for a
            protocol of one's own).
        stride: step between windows.
        model_options: constructor arguments of both models, over the protocol's
            :data:`DEFAULT_OPTIONS` (e.g. ``{"back_constraint": "kernel"}``;
            ``{"learn_measurement_width": True}`` for the thesis's model).
        sharing: the H-GPDM's share of dynamics common to all g (0: the thesis's model).
        noise_per_label: the H-GPDM gives each label its own process noise ``alpha_4,k``
            (``HGPDM(noise_per_value=True)``, estimated after the fit; needs ``sharing=0`` and
            a fixed noise); ``False`` (default): one shared ``alpha_4``, the thesis's model.
        measurement_points: VB and MAP inference route the measurement GP through at most this
            many pseudo-inputs (DTC, :meth:`~hgpdm_torch.models.GPDM.measurement_posterior`):
            a window then costs ``M^2`` instead of ``N^2``; ``None``: the exact GP;
            ``"protocol"`` (default): the protocol's CV choice, :data:`DEFAULT_MEASUREMENT_POINTS`
            (exact on Walkers, 150 on Weird Walking; 500 for a protocol of one's own).
        features: what both GP models observe
            (:func:`~hgpdm_torch.datasets.walkers.frame_features`): ``"frames"``, ``"velocity"``
            (each frame beside its change) or ``"lagged"`` (beside the previous frame; with
            either, a window of T frames gives them T - 1 rows); they forecast the frame.
            ``"protocol"`` (default): the protocol's CV choice, :data:`DEFAULT_FEATURES`
            (``"velocity"`` on Walkers, ``"lagged"`` on Weird Walking; ``"frames"`` for a
            protocol of one's own, the thesis's).
        max_folds: CV only: hold out at most this many trials (spread over the labels), for a
            quick look; ``None`` holds out every testable trial.
        executor: CV only: run the folds on it (:func:`~hgpdm_torch.parallel.get_executor`:
            local processes or a Ray cluster); the table is the serial run's. ``None``: one
            fold after the other in this process.
        progress: progress bar over folds.

    Returns:
        A :class:`ResultTable`: per window length, one row per held-out (or test) trial, an
        ``average`` row (mean over trials) and a ``SEM`` row (its standard error); ``meta``
        holds per-label means,
        the fits' convergence, the ratios to GPDM VB and which trials were missing.

    Raises:
        MissingTrialsError: before any file is read, when the folders lack trials the run
            needs (:func:`~hgpdm_torch.datasets.walkers.protocol_trials`), naming the files.
        ValueError: bad settings.
    """
    if isinstance(protocol, Protocol):
        spec = protocol
    elif protocol in FORECAST_PROTOCOLS:
        spec = PROTOCOLS[protocol]
    else:
        raise ValueError(f"protocol must be one of {FORECAST_PROTOCOLS}, got {protocol!r}")
    measurement_points = _protocol_choice("measurement_points", spec.name, measurement_points)
    fit_steps = _protocol_choice("fit_steps", spec.name, fit_steps)
    latent_dim = _protocol_choice("latent_dim", spec.name, latent_dim)
    features = _protocol_choice("features", spec.name, features)
    if not isinstance(noise_per_label, bool):
        raise TypeError(f"noise_per_label must be a bool, got {noise_per_label!r}")
    learned = [k for k in ("learn_noise", "learn_alpha") if (model_options or {}).get(k)]
    if noise_per_label and (sharing or learned):
        raise ValueError(
            "noise_per_label=True needs sharing=0 and a fixed process noise (no learn_noise or "
            f"learn_alpha), got sharing={sharing!r}, learned {learned}"
        )
    if features != "frames" and min(lengths) < 2:
        raise ValueError(
            f"{features} features need windows of at least 2 frames, got lengths "
            f"{tuple(lengths)}; pass features='frames' for shorter ones"
        )
    _, found_test = protocol_trials(spec, folder, test_folder)
    data = load_protocol(spec, "train", folder)
    options = DEFAULT_OPTIONS.get(spec.name, {}) | dict(model_options or {})
    meta: dict[str, Any] = {
        "protocol": spec.name,
        "evaluation": "test trials" if test_folder is not None else "leave-one-trial-out CV",
        "latent_dim": latent_dim,
        "model_options": {k: str(v) for k, v in options.items()},
        "sharing": sharing,
        "noise_per_label": noise_per_label,
        # recorded where it applies: fewer pseudo-inputs than training frames
        "measurement_points": measurement_points
        if measurement_points is not None and measurement_points < sum(map(len, data.sequences))
        else None,
        "fit_steps": fit_steps,
        "features": features,
        "stride": stride,
        "fps": data.fps,
        "labels": list(spec.label_names),
        "training trials": data.trials,
        "missing training trials": data.missing,
        "fits": [],
    }
    scored: list[tuple[str, str, dict[int, dict[str, Any]]]] = []  # (trial, label, rows by T)
    kwargs = {
        "lengths": tuple(lengths),
        "stride": stride,
        "latent_dim": latent_dim,
        "fit_steps": fit_steps,
        "options": options,
        "sharing": sharing,
        "noise_per_label": noise_per_label,
        "measurement_points": measurement_points,
        "features": features,
    }
    if found_test is not None:  # motions from test_folder only, skeletons also from folder
        test = load_trials(
            found_test.found,
            [test_folder, folder],
            downsample=spec.downsample,
            label_names=spec.label_names,
        )
        meta["test trials"], meta["missing test trials"] = test.trials, found_test.missing_trials
        rows, fits = _score_split(
            data.sequences, data.labels, test.sequences, test.labels, **kwargs
        )
        meta["fits"].append(fits)
        for j, name in enumerate(test.trials):
            label = test.label_names[int(test.labels[j])]
            scored.append((name, label, {T: rows[T][j] for T in lengths}))
    else:
        folds, untestable = loto_folds(data.labels)
        folds = spread_folds(folds, data, max_folds)
        meta["not testable by leave-one-trial-out"] = [data.trials[j] for j in untestable]
        job = partial(_score_fold, data.sequences, data.labels, kwargs)
        done = held_out(folds, job, executor=executor, progress=progress, desc=spec.name)
        for (_, held), (rows, fits) in zip(folds, done, strict=True):
            fits["held out"] = data.trials[held[0]]
            meta["fits"].append(fits)
            label = data.label_names[int(data.labels[held[0]])]
            scored.append((data.trials[held[0]], label, {T: rows[T][0] for T in lengths}))
    return _table(spec.table, spec.name, scored, tuple(lengths), meta)


def _score_fold(
    sequences: list[torch.Tensor],
    labels: torch.Tensor,
    kwargs: dict[str, Any],
    k: int,
    train: list[int],
    held: list[int],
) -> tuple[dict[int, list[dict[str, Any]]], dict[str, Any]]:
    """Fold ``k`` of the leave-one-trial-out CV: :func:`_score_split` on the trials ``train``
    and ``held`` (module-level, so that it pickles to an executor)."""
    parts = [([sequences[i] for i in idx], labels[idx]) for idx in (train, held)]
    return _score_split(*parts[0], *parts[1], **kwargs)


def _table(
    thesis_table: str,
    protocol: str,
    scored: list[tuple[str, str, dict[int, dict[str, Any]]]],
    lengths: tuple[int, ...],
    meta: dict[str, Any],
) -> ResultTable:
    columns = ["T", "trial", "label", "windows", *METHODS, "accuracy", "90% set coverage",
               "ProMP accuracy"]  # fmt: skip
    table = ResultTable(
        f"{protocol} ({thesis_table}): next-pose RMSE (standardised) per "
        f"{'test' if meta['evaluation'] == 'test trials' else 'held-out'} trial",
        columns,
        meta=meta,
    )
    summary: dict[str, Any] = {}
    for T in lengths:
        for trial, label, rows in scored:
            row = rows[T]
            table.add(
                T=T,
                trial=trial,
                label=label,
                windows=row["windows"],
                accuracy=row["accuracy"],
                **{"90% set coverage": row["coverage"], "ProMP accuracy": row["ProMP accuracy"]},
                **{m: row[m] for m in METHODS},
            )
        cells: dict[str, Any] = {"T": T, "trial": "average", "label": "all"}
        sem: dict[str, Any] = {"T": T, "trial": "SEM", "label": "all"}
        cells["windows"] = sum(r[T]["windows"] for _, _, r in scored)
        for m in METHODS:
            cells[m], sem[m] = mean_sem([r[T][m] for _, _, r in scored])
        cells["accuracy"] = mean_sem([r[T]["accuracy"] for _, _, r in scored])[0]
        cells["90% set coverage"] = mean_sem([r[T]["coverage"] for _, _, r in scored])[0]
        cells["ProMP accuracy"] = mean_sem([r[T]["ProMP accuracy"] for _, _, r in scored])[0]
        table.add(**cells)
        table.add(**sem)
        labels = sorted({lab for _, lab, _ in scored})
        summary[str(T)] = {
            "VB H-GPDM / GPDM VB": cells["VB H-GPDM"] / cells["GPDM VB"],
            "per label": {
                lab: {
                    m: mean_sem([r[T][m] for _, lb, r in scored if lb == lab])[0]
                    for m in (*METHODS, "accuracy", "ProMP accuracy")
                }
                for lab in labels
            },
        }
    meta["summary"] = summary
    return table


def report(table: ResultTable, out: Path | None) -> None:
    """Print a CMU experiment's table and the trials it did not find; write it to ``out``."""
    print(table.to_markdown(".3f"))
    for key in ("missing training trials", "missing test trials"):
        if table.meta.get(key):
            print(f"{key}: {', '.join(table.meta[key])}")
    if out is not None:
        table.to_json(out)


def main(argv: list[str]) -> int:
    """``hgpdm walkers [--protocol walkers|weird-walking] [--data DIR] [--test-data DIR]
    [--lengths 5 10] [--latent-dim DX] [--fit-steps N] [--stride 2] [--out table.json]
    [--workers W] [--ray-address ADDRESS]``."""
    parser = argparse.ArgumentParser(prog="hgpdm walkers", description=__doc__)
    parser.add_argument("--protocol", choices=FORECAST_PROTOCOLS, default="walkers")
    parser.add_argument("--data", type=Path, default=Path("../shared/data/cmu"))
    parser.add_argument(
        "--test-data",
        type=Path,
        default=None,
        help="score the protocol's test trials found in this folder (default: leave-one-trial-"
        "out CV within the training trials)",
    )
    parser.add_argument("--lengths", nargs="+", type=positive_int, default=[5, 10])
    parser.add_argument(
        "--latent-dim",
        type=positive_int,
        default=None,
        help="Dx of both models (default: the protocol's choice by leave-one-trial-out CV, "
        + ", ".join(f"{k} {v}" for k, v in DEFAULT_LATENT_DIM.items())
        + ")",
    )
    parser.add_argument(
        "--fit-steps",
        type=positive_int,
        default=40 if SMOKE else None,
        help="maximum MAP steps per fit (default: the protocol's choice by leave-one-trial-out "
        "CV, " + ", ".join(f"{k} {v}" for k, v in DEFAULT_FIT_STEPS.items()) + ")",
    )
    parser.add_argument("--stride", type=positive_int, default=4 if SMOKE else 2)
    parser.add_argument(
        "--max-folds", type=positive_int, default=2 if SMOKE else None, help="CV: at most N folds"
    )
    parser.add_argument("--back-constraint", choices=("kernel", "mlp"), default=None)
    parser.add_argument("--learn-noise", action="store_true", help="learn alpha_4 (MAP)")
    parser.add_argument(
        "--sharing",
        type=float,
        default=0.0,
        help="H-GPDM: share of the dynamics common to all g, in [0, 1) (default 0)",
    )
    parser.add_argument(
        "--noise-per-label",
        action="store_true",
        help="H-GPDM: a process noise alpha_4 per label, estimated after the fit (needs "
        "--sharing 0 and no --learn-noise; default: one shared alpha_4, the thesis's)",
    )
    parser.add_argument(
        "--learn-measurement-width",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="learn the RBF measurement width by MAP (the thesis's model) or keep its initial "
        "value (default: the protocol's choice by leave-one-trial-out CV: kept on Walkers, "
        "learned on Weird Walking)",
    )
    parser.add_argument(
        "--measurement-points",
        type=int_at_least(0),
        default=None,
        help="inference routes the measurement GP through at most M pseudo-inputs (DTC; exact "
        "when N <= M; 0: always exact; default: the protocol's choice by leave-one-trial-out "
        "CV, " + ", ".join(f"{k} {v}" for k, v in DEFAULT_MEASUREMENT_POINTS.items()) + ")",
    )
    parser.add_argument(
        "--features",
        choices=FRAME_FEATURES,
        default=None,
        help="what the GP models observe: the frames, each beside its change (velocity) or "
        "beside the previous frame (lagged) (default: the protocol's choice by leave-one-trial-"
        "out CV, " + ", ".join(f"{k} {v}" for k, v in DEFAULT_FEATURES.items()) + ")",
    )
    parser.add_argument("--out", type=output_file, default=None, help="write the table as JSON")
    add_executor_arguments(parser, "the cross-validation folds")
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="progress bar over the folds (default on)",
    )
    parser.add_argument(
        "--compare",
        nargs="+",
        type=Path,
        default=None,
        metavar="TABLE",
        help="instead of a run: compare the JSON tables of earlier runs (options, ratios, "
        "RMSE per label) and print / --out that comparison",
    )
    args = parser.parse_args(argv)
    if args.compare is not None:
        missing = [str(p) for p in args.compare if not p.is_file()]
        if missing:
            parser.error(f"--compare: no such file {', '.join(missing)}")
        try:  # each file named, so a wrong or cut-short one is found at once
            table = compare_runs([ResultTable.from_json(p) for p in args.compare], args.compare)
        except ValueError as err:
            parser.error(f"--compare: {err}")
        print(table.to_markdown(".3f"))
        if args.out is not None:
            table.to_json(args.out)
        return 0
    options: dict[str, Any] = {"learn_noise": args.learn_noise}
    if args.learn_measurement_width is not None:
        options["learn_measurement_width"] = args.learn_measurement_width
    if args.back_constraint is not None:
        options["back_constraint"] = args.back_constraint
    if not 0.0 <= args.sharing < 1.0:
        parser.error(f"--sharing must lie in [0, 1), got {args.sharing}")
    if args.noise_per_label and (args.sharing or args.learn_noise):
        parser.error("--noise-per-label needs --sharing 0 and no --learn-noise")
    for name, path in (("--data", args.data), ("--test-data", args.test_data)):
        if path is not None and not path.is_dir():
            parser.error(f"{name} {path} is not a folder (it needs the CMU files; docs, Walking)")
    if args.test_data is not None and ((args.workers or 1) > 1 or args.ray_address is not None):
        parser.error("--workers and --ray-address run the CV folds; --test-data has none")
    spec = PROTOCOLS[args.protocol]
    try:
        found = protocol_trials(spec, args.data, args.test_data, ("--data", "--test-data"))
    except MissingTrialsError as err:
        parser.error(str(err))
    for part in found:
        if part is not None:
            print(f"hgpdm walkers: {part.describe()}", file=sys.stderr, flush=True)
    torch.set_default_dtype(torch.float64)
    executor = connect(parser, args.workers, args.ray_address, local=True)
    try:
        table = walkers(
            args.protocol,
            folder=args.data,
            test_folder=args.test_data,
            lengths=tuple(args.lengths),
            latent_dim="protocol" if args.latent_dim is None else args.latent_dim,
            fit_steps="protocol" if args.fit_steps is None else args.fit_steps,
            stride=args.stride,
            model_options=options,
            sharing=args.sharing,
            noise_per_label=args.noise_per_label,
            measurement_points="protocol"
            if args.measurement_points is None
            else args.measurement_points or None,
            features="protocol" if args.features is None else args.features,
            max_folds=args.max_folds,
            executor=executor,
            progress=args.progress,
        )
    finally:
        if executor is not None:
            executor.close()
    report(table, args.out)
    return 0
