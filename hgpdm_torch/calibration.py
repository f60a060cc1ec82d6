r"""Calibration of intention posteriors: how often credible sets hold the truth, and the
evidence temperature that makes them hold it as often as they claim.

A posterior ``p(g | z)`` over K values is *calibrated* when its 90% credible sets (the smallest
sets of values with at least 90% of the mass) hold the true value about 90% of the time on
held-out data. A misspecified model (here: GP dynamics fitted to a few training sequences,
Gaussian approximations of ``q``) counts its evidence too strongly, and its sets are too small.

*Tempering* (a power likelihood; Grünwald 2012, Holmes & Walker 2017; for classifiers
"temperature scaling", Guo et al. 2017) divides the log evidence by ``T > 0``:
``p_T(g | z) ∝ p(g) exp(E(g) / T)``, i.e. ``log p_T = log p(g) + (log p(g | z) - log p(g)) / T``
up to normalisation. ``T = 1`` is Bayes' rule; ``T > 1`` spreads the posterior. The ranking of
the values is unchanged for a uniform prior, so batch decisions keep their accuracy.
:func:`fit_temperature` chooses ``T`` by maximum likelihood of the true values of held-out
decisions (the posteriors must come from a model that did not see them, e.g. grouped
cross-validation within the training data); ``infer_intention(..., temperature=T)`` and
``OnlineIntentionFilter(..., temperature=T)`` apply it.

Shapes: ``[..., K]`` posteriors over K values, ``[...]`` integer truths.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from scipy.optimize import minimize_scalar

from .validation import as_tensor, check_probability, real_scalar

__all__ = [
    "calibration",
    "check_temperature",
    "credible_set",
    "fit_temperature",
    "grid_index",
    "temper",
]

#: Search interval of :func:`fit_temperature` (inverse temperatures 1e-3 ... 1e3).
TEMPERATURE_BOUNDS = (1e-3, 1e3)


def check_temperature(temperature: Any) -> float:
    """``temperature`` as a positive finite float.

    Raises:
        TypeError: not a real number (or 0-dim real tensor); ValueError: not positive and
            finite.
    """
    value = real_scalar(temperature, "temperature")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"temperature must be positive and finite, got {temperature!r}")
    return value


def _log_probabilities(log_prob: Any, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``log_prob`` as a floating tensor ``[..., K]``; ``-inf`` (probability 0) is allowed,
    NaN and ``+inf`` are not."""
    try:  # a tensor stays on its device (not torch's default one)
        device = log_prob.device if isinstance(log_prob, torch.Tensor) else None
        lp = torch.as_tensor(log_prob, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise TypeError(f"log_prob must be a real array [..., K]: {err}") from err
    if not lp.is_floating_point():
        lp = lp.double()
    if lp.dim() < 1 or lp.shape[-1] < 2:
        raise ValueError(f"log_prob must be [..., K] with K >= 2, got shape {tuple(lp.shape)}")
    if bool(torch.isnan(lp).any()) or bool((lp == math.inf).any()):
        raise ValueError("log_prob holds NaN or +inf")
    if bool((lp == -math.inf).all(-1).any()):
        raise ValueError("log_prob gives some decision probability 0 for every value")
    return lp


def _probabilities(log_prob: Any, truth: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """``log_prob [N, K]`` (float64, normalised) and ``truth [N]`` (int64) from any leading
    shape, with the checks shared by this module."""
    lp = _log_probabilities(log_prob, torch.float64)
    t = torch.as_tensor(truth, device=lp.device)
    if t.is_floating_point() or t.dtype == torch.bool or t.is_complex():
        raise TypeError(f"truth must hold integer class indices, got {t.dtype}")
    if t.shape != lp.shape[:-1]:
        raise ValueError(
            f"truth must have the leading shape of log_prob {tuple(lp.shape[:-1])}, got "
            f"{tuple(t.shape)}"
        )
    k = lp.shape[-1]
    if t.numel() and bool(((t < 0) | (t >= k)).any()):
        raise ValueError(f"truth must be class indices in [0, {k - 1}]")
    lp = lp.reshape(-1, k)
    return lp - torch.logsumexp(lp, -1, keepdim=True), t.reshape(-1).long()


def intention_log_prior(
    prior: Any, k: int, dtype: torch.dtype, device: torch.device | str | None = None
) -> torch.Tensor:
    """``[K]`` normalised log prior over K intention values (default uniform), in ``dtype`` on
    ``device`` (default: ``prior``'s device, else torch's default device)."""
    if prior is None:
        return torch.full((k,), -math.log(k), dtype=dtype, device=device)
    p = as_tensor(prior, "prior", ndim=1, dtype=dtype, device=device)
    if p.shape[0] != k:
        raise ValueError(f"prior must have K = {k} entries (one per intention), got {p.shape[0]}")
    check_probability(p, "prior")
    return p.clamp_min(torch.finfo(dtype).tiny).log()


def temper(log_prob: Any, temperature: float, *, prior: Any = None) -> torch.Tensor:
    """The tempered posterior ``log p_T(g | z) = log p(g) + (log p(g | z) - log p(g)) / T``,
    normalised (module docstring).

    Args:
        log_prob: ``[..., K]`` log posterior (normalised or not).
        temperature: ``T > 0``.
        prior: ``[K]`` prior probabilities the posterior was computed with (default uniform).

    Returns:
        ``[..., K]`` normalised log posterior.

    Raises:
        TypeError, ValueError: a bad temperature, ``log_prob`` with NaN or ``+inf``, or a prior
            that is not a probability vector over the K values.
    """
    t = check_temperature(temperature)
    lp = _log_probabilities(log_prob)
    log_prior = intention_log_prior(prior, lp.shape[-1], lp.dtype, lp.device)
    out = log_prior + (lp - log_prior) / t
    return out - torch.logsumexp(out, -1, keepdim=True)


def fit_temperature(
    log_prob: Any,
    truth: Any,
    *,
    prior: Any = None,
    bounds: tuple[float, float] = TEMPERATURE_BOUNDS,
) -> float:
    """The evidence temperature ``T`` that maximises the likelihood of the true values,
    ``T* = argmin_T -sum_n log p_T(g_n | z_n)`` (:func:`temper`).

    The objective is convex in ``1 / T`` (a log-sum-exp of a linear function of it, minus a
    linear one), so a bounded scalar search finds the global minimum. Fit it on posteriors of
    held-out data (a model that saw the data is over-confident on it).

    Args:
        log_prob: ``[..., K]`` log posteriors at ``T = 1`` (e.g. ``belief.log_prob``).
        truth: ``[...]`` true value indices in ``[0, K)``.
        prior: ``[K]`` prior the posteriors were computed with (default uniform).
        bounds: search interval of ``T``.

    Returns:
        ``T``; at a bound when the optimum lies beyond it (e.g. ``bounds[1]`` when the
        posteriors carry no information about the truth at all).

    Raises:
        ValueError: bad shapes, classes out of range, NaN, no decisions, or bad bounds.
    """
    lp, t = _probabilities(log_prob, truth)
    if t.numel() == 0:
        raise ValueError("fit_temperature needs at least one decision")
    lo, hi = (float(b) for b in bounds)
    if not (0 < lo < hi and math.isfinite(hi)):
        raise ValueError(f"bounds must satisfy 0 < low < high < inf, got {bounds!r}")
    log_prior = intention_log_prior(prior, lp.shape[-1], lp.dtype, lp.device)
    # evidence relative to the prior; -inf (a value the posterior excludes) stays -inf at any T
    evidence = (lp - log_prior).clamp_min(-1e300)

    def nll(beta: float) -> float:
        s = log_prior + beta * evidence
        return float((torch.logsumexp(s, -1) - s.gather(-1, t[:, None])[:, 0]).mean())

    res = minimize_scalar(
        nll, bounds=(1.0 / hi, 1.0 / lo), method="bounded", options={"xatol": 1e-6}
    )
    return float(1.0 / res.x)


def credible_set(prob: torch.Tensor, level: float = 0.9) -> torch.Tensor:
    """``[..., K]`` bool mask of the smallest set of values holding at least ``level`` of the
    mass of ``prob [..., K]`` (values ranked by probability; a value is in the set when the
    mass ranked above it is below ``level``)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    p, order = prob.sort(-1, descending=True)
    keep = (p.cumsum(-1) - p) < level  # mass of the values ranked above
    return torch.zeros_like(keep).scatter(-1, order, keep)


def calibration(prob: Any, truth: Any, level: float = 0.9) -> dict[str, float]:
    """Calibration of posteriors ``prob [..., K]`` against true value indices ``truth [...]``.

    Args:
        prob: ``[..., K]`` probabilities (each row non-negative, summing to 1).
        truth: ``[...]`` integer indices of the true values.
        level: credible level of the sets (default 0.9).

    Returns:
        ``coverage``: how often the :func:`credible_set` holds the truth (a calibrated
        posterior gives at least ``level``, the mean mass of its sets); ``set_size``: its mean
        size; ``ece``: expected calibration error of the top value over 10 equal-width
        confidence bins; ``nll``: mean negative log probability of the truth.

    Raises:
        ValueError: rows that are not probability vectors, bad shapes or indices, or a level
            outside (0, 1).
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    p = as_tensor(prob, "prob", dtype=torch.float64)
    if p.dim() < 1:
        raise ValueError(f"prob must be [..., K], got shape {tuple(p.shape)}")
    check_probability(p, "prob")
    lp, t = _probabilities(p.clamp_min(0).log(), truth)
    p = lp.exp()
    inside = credible_set(p, level)
    conf, top = p.max(-1)
    correct = (top == t).double()
    bins = torch.clamp((conf * 10).long(), max=9)
    ece = sum(
        float((bins == b).double().mean())
        * abs(float(correct[bins == b].mean() - conf[bins == b].mean()))
        for b in range(10)
        if bool((bins == b).any())
    )
    return {
        "coverage": float(inside.gather(-1, t[:, None]).double().mean()),
        "set_size": float(inside.sum(-1).double().mean()),
        "ece": ece,
        "nll": float(-lp.gather(-1, t[:, None]).mean()),
    }


def grid_index(targets: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Index of the grid value nearest to each target: the value a credible set over the grid
    must hold to cover the target.

    Args:
        targets: ``[...]`` finite targets.
        grid: ``[K]`` finite grid values.

    Returns:
        ``[...]`` int64 indices into ``grid``.

    Raises:
        ValueError: a grid that is not 1-D and non-empty, or non-finite values.
    """
    targets = as_tensor(targets, "targets")
    grid = as_tensor(grid, "grid", ndim=1)
    if grid.numel() == 0:
        raise ValueError("grid must hold at least one value")
    return (targets[..., None] - grid.to(targets.dtype)).abs().argmin(-1)
