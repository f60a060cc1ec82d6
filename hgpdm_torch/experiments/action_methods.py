"""The methods of the action-recognition experiments (thesis Table 3.3) and their timed decisions,
shared by the BasicMotions and MSRC-12 protocols: the IDDM of the table and its batch and online
rows, the sliding-window baselines (SVM, GP classification, per-class HMMs), a ProMP per class
whose prefix likelihood (its phase estimated) gives the class posterior, the IDDM rows'
evidence temperatures by cross-validation within the training data, and the scores of a run
(CPU time per decision, 90% credible-set coverage, confusion matrices).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch

from ..baselines import HMMClassifier, ProMPClassifier, WindowGPC, WindowSVM
from ..calibration import fit_temperature
from ..crossval import held_out
from ..fitting import FitResult
from ..inference.intention import IntentionBelief, OnlineIntentionFilter, infer_intention
from ..models import IDDM
from ..progress import tqdm

__all__ = [
    "FoldRun",
    "Method",
    "Split",
    "TableRows",
    "check_calibration_folds",
    "confusion",
    "coverage",
    "decide",
    "fit_iddm",
    "fit_temperatures",
    "iddm_methods",
    "run_fold",
    "table_methods",
]

# a method maps test sequences [M, T, Dz] to a decision after every frame: [M, T] labels
# (long), or [M, T, K] log class probabilities (the IDDM's beliefs, whose 90% credible sets
# are scored too)
Method = Callable[[torch.Tensor], torch.Tensor]


def fit_iddm(
    z_train: torch.Tensor,
    y_train: torch.Tensor,
    num_classes: int,
    latent_dim: int,
    fit_steps: int,
    seed: int,
    progress: bool,
    *,
    alpha4: float = 1e-2,
    noise_per_value: bool = False,
) -> tuple[IDDM, FitResult]:
    """The IDDM of Table 3.3: discrete g, linear measurement kernel, MAP fit (L-BFGS) on
    ``z_train [J, T, Dz]`` labelled ``y_train [J]``; transition ``alpha = (0.9, 0.3, 0.1,
    alpha4)``, and with ``noise_per_value`` a process noise per class estimated after the fit
    (:class:`~hgpdm_torch.models.HGPDM`)."""
    torch.manual_seed(seed)
    model = IDDM(
        list(z_train),
        y_train,
        latent_dim,
        intention="discrete",
        measurement="linear",
        num_values=num_classes,
        alpha=(0.9, 0.3, 0.1, alpha4),
        noise_per_value=noise_per_value,
    )
    return model, model.fit(fit_steps, progress=progress)


def iddm_methods(
    model: IDDM,
    *,
    windows: Sequence[int],
    forgettings: Sequence[float],
    state_prior: str,
    temperatures: dict[str, float] | None = None,
) -> list[tuple[str, Method]]:
    """The IDDM rows of Table 3.3 (batch windows, online forgettings), each returning log
    beliefs ``[M, T, K]``; ``temperatures`` maps a row's name to its evidence temperature
    (default 1, the thesis's inference)."""
    temps = temperatures or {}
    jobs: list[tuple[str, Method]] = []
    for w in windows:
        name = f"IDDM batch n={w}"

        def batch(z: torch.Tensor, w: int = w, temp: float = temps.get(name, 1.0)) -> torch.Tensor:
            return infer_intention(
                model, z, window=w, state_prior=state_prior, temperature=temp
            ).log_prob

        jobs.append((name, batch))
    for eps in forgettings:
        name = f"IDDM online eps={eps}"

        def online(
            z: torch.Tensor, eps: float = eps, temp: float = temps.get(name, 1.0)
        ) -> torch.Tensor:
            f = OnlineIntentionFilter(
                model,
                forgetting=eps,
                batch_size=z.shape[0],
                state_prior=state_prior,
                temperature=temp,
            )
            return torch.stack([f.update(z[:, t]).log_prob for t in range(z.shape[1])], 1)

        jobs.append((name, online))
    return jobs


def table_methods(
    model: IDDM,
    z_train: torch.Tensor,
    y_train: torch.Tensor,
    meta: dict[str, Any],
    *,
    windows: Sequence[int],
    forgettings: Sequence[float],
    baseline_window: int,
    seed: int,
    state_prior: str,
    temperatures: dict[str, float] | None = None,
) -> list[tuple[str, Method]]:
    """The methods of Table 3.3, baselines fitted on ``z_train [J, T, Dz]``, ``y_train [J]``;
    the IDDM's first-state prior ``state_prior`` (see :func:`infer_intention`) and evidence
    ``temperatures`` (:func:`iddm_methods`).

    Returns ``(name, method)`` pairs in table order; a method left out is named in
    ``meta["skipped"]``.
    """
    jobs = iddm_methods(
        model,
        windows=windows,
        forgettings=forgettings,
        state_prior=state_prior,
        temperatures=temperatures,
    )
    train = list(z_train)
    svm = WindowSVM(baseline_window).fit(train, y_train)
    jobs.append((f"SVM n={baseline_window}", svm.predict))
    gpc = WindowGPC(baseline_window, seed=seed).fit(train, y_train)
    jobs.append((f"GPC n={baseline_window}", gpc.predict))
    promp = ProMPClassifier(seed=seed).fit(train, y_train)
    meta["promp_options"] = {k: str(v) for k, v in promp.options.items()}
    jobs.append(("ProMP (phase estimated)", promp.predict_log_proba))
    try:
        hmm = HMMClassifier(states=3, window=baseline_window, seed=seed).fit(train, y_train)
    except ImportError:
        meta["skipped"] = "HMM (hmmlearn not installed)"
        return jobs
    jobs.append((f"HMM n={baseline_window}", hmm.predict))
    return jobs


# one inner split of the training data: (z_fit [J, T, Dz], y_fit [J], z_val [V, T, Dz], y_val [V])
Split = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def fit_temperatures(
    splits: Sequence[Split],
    num_classes: int,
    latent_dim: int,
    fit_steps: int,
    seed: int,
    *,
    windows: Sequence[int],
    forgettings: Sequence[float],
    state_prior: str,
    progress: bool = False,
    **iddm: Any,
) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """Evidence temperature of each IDDM row by cross-validation within the training data.

    For each inner split an IDDM is fitted on ``z_fit`` as the row's own model is (``iddm``:
    the keyword arguments of :func:`fit_iddm` that it was fitted with), its beliefs
    at ``T = 1`` after every frame of the held-out ``z_val`` are pooled over the splits, and
    :func:`~hgpdm_torch.inference.fit_temperature` gives the ``T`` that maximises the
    likelihood of the true classes. For the batch rows this is exact temperature scaling; the
    online filter mixes its state under the belief, so there ``T`` is the scaling that fits the
    untempered beliefs best.

    Returns:
        ``{row name: T}`` and the ``FitResult.summary()`` of the inner fits.
    """

    def beliefs(k: int, z_fit, y_fit, z_val, y_val) -> tuple[dict, dict[str, torch.Tensor], Any]:
        """Split ``k``'s fit summary, each row's log beliefs on ``z_val`` and their truths."""
        dx = min(latent_dim, z_fit.shape[-1])
        model, fit = fit_iddm(z_fit, y_fit, num_classes, dx, fit_steps, seed, progress, **iddm)
        rows = iddm_methods(
            model, windows=windows, forgettings=forgettings, state_prior=state_prior
        )
        logs = {name: run(z_val) for name, run in rows}
        return fit.summary(), logs, y_val[:, None].expand(-1, z_val.shape[1])

    out = held_out(splits, beliefs, progress=progress, desc="calibration")
    fits = [fit for fit, _, _ in out]
    logs = {name: [split[name] for _, split, _ in out] for name in out[0][1]}
    truth = torch.cat([truth for _, _, truth in out])
    temps = {name: fit_temperature(torch.cat(parts), truth) for name, parts in logs.items()}
    return temps, fits


class TableRows(NamedTuple):
    """The choices that make Table 3.3's rows, the same in every protocol: the IDDM's batch
    ``windows``, its online ``forgettings``, the sliding-window baselines'
    ``baseline_window``, the IDDM's first-state prior ``state_prior`` and the ``seed`` of the
    fits and baselines (the keywords of :func:`table_methods`)."""

    windows: Sequence[int]
    forgettings: Sequence[float]
    baseline_window: int
    state_prior: str
    seed: int


class FoldRun(NamedTuple):
    """One training/test split of a protocol (:func:`run_fold`): the IDDM and its fit, the
    IDDM rows' evidence temperatures with the calibration fits' summaries (``{}`` and ``[]``
    uncalibrated), and every method's :func:`decide` output on the test sequences."""

    model: IDDM
    fit: FitResult
    temperatures: dict[str, float]
    calibration_fits: list[dict[str, Any]]
    decisions: list[tuple[str, torch.Tensor, float, torch.Tensor | None]]


def run_fold(
    z_train: torch.Tensor,
    y_train: torch.Tensor,
    z_test: torch.Tensor,
    num_classes: int,
    latent_dim: int,
    fit_steps: int,
    rows: TableRows,
    meta: dict[str, Any],
    *,
    splits: Sequence[Split] | None = None,
    calibration_dim: int | None = None,
    progress: bool = False,
    **iddm: Any,
) -> FoldRun:
    """Table 3.3 on one split, as every protocol runs it: the IDDM fitted on ``z_train [J, T,
    Dz]``, ``y_train [J]`` (:func:`fit_iddm`, with ``iddm``), its rows' evidence temperatures
    from the inner ``splits`` (:func:`fit_temperatures`, IDDMs of ``calibration_dim`` latent
    dims, default ``latent_dim``; ``None``: ``T = 1``), and every method of
    :func:`table_methods` (notes in ``meta``) deciding on ``z_test [M, T, Dz]``."""
    model, fit = fit_iddm(
        z_train, y_train, num_classes, latent_dim, fit_steps, rows.seed, progress, **iddm
    )
    temps: dict[str, float] = {}
    inner_fits: list[dict[str, Any]] = []
    if splits is not None:
        temps, inner_fits = fit_temperatures(
            splits, num_classes, latent_dim if calibration_dim is None else calibration_dim,
            fit_steps, rows.seed, windows=rows.windows, forgettings=rows.forgettings,
            state_prior=rows.state_prior, progress=progress, **iddm,
        )  # fmt: skip
    methods = table_methods(model, z_train, y_train, meta, temperatures=temps, **rows._asdict())
    return FoldRun(model, fit, temps, inner_fits, decide(methods, z_test, progress))


def check_calibration_folds(folds: Any, most: int, what: str) -> None:
    """``folds`` must be an int in ``[2, most]`` (``most``: the number of ``what``)."""
    if isinstance(folds, bool) or not isinstance(folds, int) or not 2 <= folds <= most:
        raise ValueError(
            f"calibration_folds must be None or an int in [2, {most}] (the {what}), got {folds!r}"
        )


def decide(
    jobs: list[tuple[str, Method]], z_test: torch.Tensor, progress: bool
) -> list[tuple[str, torch.Tensor, float, torch.Tensor | None]]:
    """Every method's decisions ``[M, T]`` on ``z_test [M, T, Dz]``, its CPU ms/decision and,
    for a method that returns log probabilities, the ``[M, T, K]`` mask of its 90% credible
    sets."""
    out = []
    for name, run in tqdm(jobs, disable=not progress, desc="methods", leave=False):
        start = time.process_time()
        result = run(z_test)
        seconds = time.process_time() - start
        credible = None
        if result.is_floating_point():
            credible = IntentionBelief(result.exp(), result, torch.empty(0)).credible_set(0.9)
            result = result.argmax(-1)
        out.append((name, result, 1e3 * seconds / result.numel(), credible))
    return out


def coverage(credible: torch.Tensor | None, truth: torch.Tensor) -> float | None:
    """% of decisions whose 90% credible set ``[M, T, K]`` holds the true class ``[M]``."""
    if credible is None:
        return None
    hit = credible.gather(-1, truth[:, None, None].expand(-1, credible.shape[1], 1))
    return 100.0 * float(hit.double().mean())


def confusion(pred: torch.Tensor, truth: torch.Tensor, k: int) -> np.ndarray:
    """``[k, k]`` counts (rows true, columns predicted) of ``pred [M, T]`` against ``truth``
    (``[M, 1]`` or ``[M, T]``)."""
    m = np.zeros((k, k), dtype=int)
    np.add.at(m, (truth.expand_as(pred).flatten().numpy(), pred.flatten().numpy()), 1)
    return m
