r"""Intention inference with the IDDM: batch (Algorithm 3.1) and online (Algorithm 3.2).

Both algorithms score every value of a discrete or discretised intention ``g`` (a grid of K
values) with a variational bound built from Gaussian (moment-matched) smoothing distributions
``q`` of the latent states (thesis Sec. 3.3-3.4):

- **batch** (:func:`infer_intention`, Algorithm 3.1): for each ``g`` the GP-RTSS smoother gives
  ``q_g(x_{1:T})`` and the bound of Eq. 22 is evaluated in full,
  ``B(g) = log p(g) + E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q_g)``.
  Algorithm 3.1 (line 3) prints only the transition part; the other terms also depend on ``g``
  through ``q_g``, so they are kept (with a shared ``q`` they are constants, which is why the
  online algorithm can drop them).
- **online** (:class:`OnlineIntentionFilter`, Algorithm 3.2): one Gaussian ``q`` over the
  latent state shared by all ``g`` and the recursion ``B_t(g) = E_t(g) + (1 - eps) B_{t-1}(g)``
  with the forgetting factor ``eps``. The evidence ``E_t(g)`` is either the thesis's
  ``Q_{t-1}(g)`` from one-step filtering and one-step backward smoothing under the current belief
  (``evidence="bound"``), or (the default) the GP-ADF predictive likelihood
  ``log q(z_t | z_{1:t-1}, g)`` from the shared ``q``, which is calibrated where the bound with a
  shared ``q`` is over-confident (see the class docstring).

``Q_t(g) = E_q[log p(x_{t+1} | x_t, g)]`` (Sec. 3.3.2 and DESIGN.md sec. 7). With
``q~ = N(m, S)``, the moment-matched Gaussian of ``p(x_{t+1} | x_t, g) q'(x_t)``, the
transition is replaced by the conditional of ``q~`` (a statistical linearisation),
``q~(x_{t+1} | x_t) = N(A x_t + c, V)``, and the expectation under ``q(x_t, x_{t+1})`` is exact.
With ``q' = q(x_t)`` this equals ``-KL(q || q~) - H(q(x_t, x_{t+1})) + H(q(x_t))`` of DESIGN.md;
with ``q'`` the filtered ``q(x_t | z_{1:t})`` (the online ``"bound"`` default) it differs from
that only by terms shared by all ``g``, and the K moment matchings of the prediction step are
reused.

Where the speed comes from (DESIGN.md sec. 8): the transition kernel of the IDDM is
``alpha_1 exp(-alpha_2/2 |x - x'|^2) phi(g, g')`` (``phi`` an RBF in g, or ``delta`` for a
discrete g). The online input ``q(x_{t-1})`` is shared by all K intentions, so the ``N x N``
expectation ``psi2`` over ``x`` is computed once per stream and step; and as ``g`` is constant
within a training sequence, the N training points form U groups of equal ``g``. All K second
moments and traces then follow from ``U x U`` group sums of ``psi2``:
``beta_k^T psi2 beta_k = sum_uv phi_ku phi_kv (beta_u^T psi2_uv beta_v)`` — no ``N x N`` work
per intention. See :class:`SharedTransition` (optionally on M < N pseudo-inputs, Sec. 3.3.3);
a linear measurement kernel is updated in closed form (:class:`LinearMeasurement`).

Observations: a row of NaN is a missing observation everywhere. Other rows that the filter
cannot use (+-inf, partly NaN, or more than ``outlier_sd`` = 100 training standard deviations
from the training mean in a channel; :class:`~hgpdm_torch.inference.filtering.ObservationCheck`)
make the batch algorithm raise a ``ValueError`` naming the window, step and channel; the online
filter rejects them for their stream only and restarts a stream whose update fails numerically,
without touching the others (:class:`OnlineIntentionFilter`).

Shapes: ``B`` streams, ``K`` intention values, ``T`` steps, ``Dx`` latent, ``Dz`` observed,
``Dg`` intention dims, ``N`` transition training points.
"""

from __future__ import annotations

import copy
import functools
import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from sklearn.cluster import KMeans
from tqdm.auto import tqdm

from .. import settings
from ..expectations import Term, kernel_leaves, split_terms, term_psi1_grad, term_psi2
from ..gaussian import (
    conditional,
    entropy,
    expected_log_density,
    independent_joint,
    log_density_terms,
    mixture_moments,
    rts_step,
)
from ..gp import GPPosterior
from ..linalg import CholeskyError, cholesky_logdet, psd_cholesky, symmetrize
from ..models import HGPDM
from ..validation import as_tensor, check_choice
from .calibration import check_temperature, credible_set, intention_log_prior
from .filtering import (
    DEFAULT_OUTLIER_SD,
    ObservationCheck,
    _as_observations,
    _bad_observation,
    _real_scalar,
    filter_sequence,
    gp_adf_update,
    smooth,
)

__all__ = [
    "IntentionBelief",
    "LinearMeasurement",
    "OnlineIntentionFilter",
    "PRECISION_LIMIT",
    "SharedTransition",
    "STATE_PRIORS",
    "batch_bound",
    "batch_bound_terms",
    "class_state_prior",
    "expected_log_conditional",
    "infer_intention",
    "intention_grid",
]

#: What a failed update of one stream raises: a covariance that does not factorise
#: (:func:`~hgpdm_torch.linalg.psd_cholesky`: ``CholeskyError``, or ``ValueError`` for NaN/inf),
#: or a LAPACK failure. The online filter isolates the stream and restarts it.
_NUMERICAL_ERRORS = (CholeskyError, torch.linalg.LinAlgError, ValueError)
#: Streams initialised together (a measurement update is cheap; fixed ranges, see ``update``).
_INIT_CHUNK = 4096


@dataclass
class IntentionBelief:
    """A posterior over K intention values.

    Attributes:
        prob: ``[..., K]`` posterior probabilities.
        log_prob: ``[..., K]`` their logs (normalised).
        values: ``[K, Dg]`` the intention values (codes for a discrete g).
        mean: ``[..., Dg]`` posterior mean of a continuous g (``None`` for a discrete g).
        std: ``[..., Dg]`` posterior standard deviation of a continuous g (or ``None``).
        rejected: (:meth:`OnlineIntentionFilter.update` only, else ``None``) ``[B]`` bool
            (``[]`` for one ``[Dz]`` observation): the stream's observation of this update was
            bad (:class:`~hgpdm_torch.inference.filtering.ObservationCheck`) and was treated as
            missing.
        reset_streams: (:meth:`OnlineIntentionFilter.update` only) ``[B]`` bool: the stream
            failed numerically in this update (or held a non-finite state) and was restarted
            at the prior.
    """

    prob: torch.Tensor
    log_prob: torch.Tensor
    values: torch.Tensor
    mean: torch.Tensor | None = None
    std: torch.Tensor | None = None
    rejected: torch.Tensor | None = None
    reset_streams: torch.Tensor | None = None

    @classmethod
    def from_log(
        cls, log_weights: torch.Tensor, values: torch.Tensor, continuous: bool
    ) -> IntentionBelief:
        """Normalise unnormalised log weights ``[..., K]`` over ``values [K, Dg]``."""
        log_prob = log_weights - torch.logsumexp(log_weights, -1, keepdim=True)
        prob = log_prob.exp()
        if not continuous:
            return cls(prob, log_prob, values)
        # centred second moment: E[g^2] - E[g]^2 would cancel for a grid far from 0
        mean, cov = mixture_moments(prob, values)
        return cls(prob, log_prob, values, mean, cov.diagonal(dim1=-2, dim2=-1).sqrt())

    def credible_set(self, level: float = 0.9) -> torch.Tensor:
        """``[..., K]`` mask of the smallest set of values holding at least ``level`` mass."""
        return credible_set(self.prob, level)


# ------------------------------------------------------------------------------------------
# Set-up shared by both algorithms
# ------------------------------------------------------------------------------------------


def intention_grid(model: HGPDM, intentions: Any = None, num: int = 25) -> torch.Tensor:
    """The K intention values to score, ``[K, Dg]`` (codes ``[K, 1]`` for a discrete g).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.HGPDM` / ``IDDM``.
        intentions: ``[K]`` or ``[K, Dg]`` values (continuous g) or integer codes (discrete g);
            default: all codes, or ``num`` evenly spaced values over the training range
            (``Dg = 1`` only).
        num: default grid size for a continuous g.
    """
    if not isinstance(model, HGPDM):
        raise TypeError(f"model must be an HGPDM/IDDM, got {type(model).__name__}")
    dtype, device = model.latent.dtype, model.latent.device
    if intentions is None:
        if model.intention == "discrete":
            return torch.arange(model.num_values, dtype=dtype, device=device)[:, None]
        if model.intention_dim != 1:
            raise ValueError("a multi-dimensional continuous g needs an explicit intentions grid")
        g = model.intentions[:, 0]
        grid = torch.linspace(float(g.min()), float(g.max()), int(num), dtype=dtype, device=device)
        return grid[:, None]
    values = as_tensor(intentions, "intentions", dtype=dtype, device=device)
    if values.dim() == 1:
        values = values[:, None]
    if values.dim() != 2 or values.shape[0] == 0:
        raise ValueError(
            f"intentions must be a non-empty [K] or [K, Dg] grid, got {tuple(values.shape)}"
        )
    if values.shape[1] != model.intention_dim:
        raise ValueError(
            f"intentions must have Dg = {model.intention_dim} columns, got {values.shape[1]}"
        )
    if model.intention == "discrete":
        codes = values[:, 0]
        if bool((codes != codes.round()).any()) or bool(
            ((codes < 0) | (codes >= model.num_values)).any()
        ):
            raise ValueError(
                f"discrete intentions must be integer codes in [0, {model.num_values - 1}]"
            )
    return values


def _posterior_as(post: GPPosterior, dtype: torch.dtype) -> GPPosterior:
    """The same GP in another dtype (Cholesky refactorised in that dtype)."""
    if post.train_inputs.dtype == dtype:
        return post
    return GPPosterior(
        copy.deepcopy(post.kernel).to(dtype),
        post.train_inputs.to(dtype),
        post.train_targets.to(dtype),
        post.noise.to(dtype),
        code_noise=None if post.code_noise is None else post.code_noise.to(dtype),
        scale=post.scale.to(dtype),
        offset=post.offset.to(dtype),
    )


def _state_prior(
    model: HGPDM, mu0: Any, Sigma0: Any, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """Prior of the first latent state: default the empirical marginal of the training latents
    (a window may start anywhere in a movement, not only at its first frame)."""
    x = model.latent.detach()
    mu = x.mean(0) if mu0 is None else as_tensor(mu0, "mu0", ndim=1, dtype=x.dtype, device=x.device)
    if Sigma0 is None:
        d = x - x.mean(0)
        Sigma = d.T @ d / max(x.shape[0] - 1, 1)
    else:
        Sigma = as_tensor(Sigma0, "Sigma0", ndim=2, dtype=x.dtype, device=x.device)
    dx = model.latent_dim
    if mu.shape != (dx,) or Sigma.shape != (dx, dx):
        raise ValueError(
            f"mu0 and Sigma0 must have shapes [{dx}] and [{dx}, {dx}], got "
            f"{tuple(mu.shape)} and {tuple(Sigma.shape)}"
        )
    psd_cholesky(Sigma, name="Sigma0")
    return mu.to(dtype), symmetrize(Sigma).to(dtype)


STATE_PRIORS = ("marginal", "class")


def class_state_prior(
    model: HGPDM, values: torch.Tensor, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """Class-conditional prior of a window's first state, ``p(x_1 | g_k)`` for each code.

    The empirical mean and covariance of the training latents of the sequences with
    ``g = g_k`` (a window may start anywhere in a movement *of that class*). The covariance is
    shrunk towards the marginal one with the weight of ``Dx`` pseudo-frames,
    ``(n_k C_k + Dx C) / (n_k + Dx)``, so that a value with few frames still has a proper prior.

    Args:
        model: a fitted IDDM with a discrete g; values: ``[K, 1]`` codes (see
            :func:`intention_grid`); dtype: of the result.

    Returns:
        ``mu0 [K, Dx]``, ``Sigma0 [K, Dx, Dx]``.

    Raises:
        ValueError: a continuous g, or a code without training sequences.
    """
    if model.intention != "discrete":
        raise ValueError("state_prior='class' needs a discrete intention; use 'marginal'")
    x = model.latent.detach()
    frames = torch.repeat_interleave(model.intention_codes(), model.lengths)
    mu, Sigma = _state_prior(model, None, None, x.dtype)
    dx = model.latent_dim
    means, covs = [], []
    for code in values[:, 0].long().tolist():
        xk = x[frames == code]
        if xk.shape[0] == 0:
            raise ValueError(f"intention {code} has no training sequences: no class prior")
        d = xk - xk.mean(0)
        means.append(xk.mean(0))
        covs.append(symmetrize((d.T @ d + dx * Sigma) / (xk.shape[0] + dx)))
    return torch.stack(means).to(dtype), torch.stack(covs).to(dtype)


def _first_state_prior(
    model: HGPDM, values: torch.Tensor, mu0: Any, Sigma0: Any, state_prior: str, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mu0 [Dx], Sigma0 [Dx, Dx])`` for ``"marginal"``, ``([K, Dx], [K, Dx, Dx])`` for
    ``"class"``."""
    check_choice(state_prior, "state_prior", STATE_PRIORS)
    if state_prior == "marginal":
        return _state_prior(model, mu0, Sigma0, dtype)
    if mu0 is not None or Sigma0 is not None:
        raise ValueError("give either mu0/Sigma0 or state_prior='class', not both")
    return class_state_prior(model, values, dtype)


def _check_observations(z: Any, dz: int, min_ndim: int) -> torch.Tensor:
    """``z [..., Dz]`` as a floating tensor in its own precision (bad rows are kept: the caller
    classifies them with an :class:`~hgpdm_torch.inference.filtering.ObservationCheck`)."""
    z = _as_observations(z, min_ndim=min_ndim)
    if z.shape[-1] != dz:
        raise ValueError(f"z must have Dz = {dz} columns (the model's), got {z.shape[-1]}")
    return z


def _check_chunk_size(chunk_size: Any) -> int | None:
    if chunk_size is None:
        return None
    if (
        isinstance(chunk_size, bool)
        or not isinstance(chunk_size, numbers.Integral)
        or int(chunk_size) < 1
    ):
        raise ValueError(f"chunk_size must be a positive int or None, got {chunk_size!r}")
    return int(chunk_size)


# ------------------------------------------------------------------------------------------
# Statistical linearisation: E_q[log q~(y | x)]
# ------------------------------------------------------------------------------------------


def expected_log_conditional(
    lin_mean_in: torch.Tensor,
    lin_cov_in: torch.Tensor,
    lin_mean_out: torch.Tensor,
    lin_cov_out: torch.Tensor,
    lin_cross: torch.Tensor,
    q_mean_in: torch.Tensor,
    q_cov_in: torch.Tensor,
    q_mean_out: torch.Tensor,
    q_cov_out: torch.Tensor | None,
    q_cross: torch.Tensor | None,
) -> torch.Tensor:
    r"""``E_q[log q~(y | x)]`` for a jointly Gaussian linearisation ``q~`` and a Gaussian ``q``.

    ``q~(x, y) = N([a, m], [[P, C], [C^T, S]])`` gives ``q~(y | x) = N(m + A (x - a), V)`` with
    ``A = C^T P^-1`` and ``V = S - C^T P^-1 C``; under ``q(x, y)`` with means ``(mu_x, mu_y)``,
    covariances ``Sx, Sy`` and ``Sxy = Cov[x, y]``, with ``r = mu_y - m - A (mu_x - a)``::

        E = -1/2 [log|2 pi V| + tr(V^-1 (r r^T + Sy - A Sxy - Sxy^T A^T + A Sx A^T))]

    This is ``Q_t(g)`` of Sec. 3.3.2 (``x = x_t``, ``y = x_{t+1}``) and, with ``y = z_t`` observed
    (``Sy = Sxy = 0``), the measurement term ``E_q[log p(z_t | x_t)]`` of Eq. 22.

    Shapes: ``lin_*`` over ``[..., Dx]``/``[..., Dy]``; ``q_*`` broadcast against them;
    ``q_cov_out``/``q_cross`` ``None`` for an observed ``y``. Returns ``[...]``.
    """
    L = psd_cholesky(lin_cov_in, name="linearisation input covariance")
    At, V = conditional(lin_cov_out, lin_cross.transpose(-1, -2), L)
    A = At.transpose(-1, -2)  # C^T P^-1  [..., Dy, Dx]
    LV = psd_cholesky(V, name="linearised conditional covariance")
    r = q_mean_out - lin_mean_out - (A @ (q_mean_in - lin_mean_in)[..., None])[..., 0]
    E = r[..., :, None] * r[..., None, :] + A @ q_cov_in @ A.transpose(-1, -2)
    if q_cov_out is not None:
        AC = A @ q_cross
        E = E + q_cov_out - AC - AC.transpose(-1, -2)
    W = torch.linalg.solve_triangular(LV, symmetrize(E), upper=False)
    W = torch.linalg.solve_triangular(LV, W.transpose(-1, -2), upper=False)
    trace = W.diagonal(dim1=-2, dim2=-1).sum(-1)
    return log_density_terms(trace, cholesky_logdet(LV), V.shape[-1])


def _entropy(cov: torch.Tensor) -> torch.Tensor:
    """Entropy ``[...]`` of ``N(., cov [..., D, D])``."""
    return entropy(psd_cholesky(cov, name="smoothed covariance"))


# ------------------------------------------------------------------------------------------
# Moment matching of the IDDM transition for K intentions sharing one input Gaussian
# ------------------------------------------------------------------------------------------


def _dtc(posterior: GPPosterior, Z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """DTC weights ``[M, Dout]`` and variance matrix ``[M, M]`` on the pseudo-inputs ``Z``."""
    X, Y, noise = posterior.train_inputs, posterior.train_targets, posterior.noise
    if noise.dim() or posterior.code_noise is not None:
        raise ValueError(
            "inducing (the sparse DTC transition GP) needs one shared process noise; this model "
            "has a noise per intention value (noise_per_value=True): use inducing=None"
        )
    with torch.no_grad():
        Kmm = posterior.kernel(Z).to_dense()
        Kmn = posterior.kernel(Z, X).to_dense()
    Lm = psd_cholesky(Kmm, name="inducing kernel matrix K_MM")
    LA = psd_cholesky(noise * Kmm + Kmn @ Kmn.T, name="DTC matrix noise K_MM + K_MN K_NM")
    weights = torch.cholesky_solve(Kmn @ Y, LA)
    kinv = symmetrize(torch.cholesky_inverse(Lm) - noise * torch.cholesky_inverse(LA))
    return weights, kinv


def _pseudo_inputs(
    X: torch.Tensor, dx: int, m: int, num_values: int | None, discrete: bool
) -> torch.Tensor:
    """M pseudo-inputs ``[<= M, Dx + Dg]`` for the sparse transition GP (Sec. 3.3.3).

    The cost per step grows with the number of distinct intention values among the pseudo-inputs
    (the groups of :class:`SharedTransition`), so they share ``num_values`` values: the training
    intentions' K-means centres, weighted by their number of points (default
    ``round(sqrt(M))``; the training values themselves when ``M >= N``, which gives the exact GP;
    a discrete g always keeps its codes). Each value gets ``floor(M / values)`` (at least one)
    training latents of its cluster, evenly spread over the cluster's points (all of them when
    it has fewer), so there are at most M unless M is below the number of discrete codes.
    """
    uniq, group = torch.unique(X[:, dx:], dim=0, return_inverse=True)
    u = len(uniq)
    if num_values is None:
        num_values = max(1, round(math.sqrt(m))) if m < X.shape[0] else u
    if discrete or num_values >= u:
        centres, cluster = uniq, group
    else:
        counts = torch.bincount(group, minlength=u).double().cpu().numpy()
        km = KMeans(n_clusters=num_values, n_init=4, random_state=0)
        km.fit(uniq.double().cpu().numpy(), sample_weight=counts)
        centres = torch.as_tensor(km.cluster_centers_, dtype=X.dtype, device=X.device)
        cluster = torch.as_tensor(km.labels_, dtype=torch.long, device=X.device)[group]
    # the same number of points per value: groups are padded to the largest one
    per = max(1, m // len(centres))
    keep = []
    for c in range(len(centres)):
        members = torch.nonzero(cluster == c).flatten()
        pick = torch.linspace(0, len(members) - 1, min(per, len(members)), device=X.device)
        pick = pick.round().long()
        keep.append(members[pick])
    keep = torch.cat(keep)
    return torch.cat([X[keep, :dx], centres[cluster[keep]]], 1)


class SharedTransition:
    r"""Moment matching of the IDDM transition GP at one input Gaussian for all K intentions.

    For ``x ~ N(mu, Sigma)`` and each grid value ``g_k`` this gives exactly what
    :meth:`GPPosterior.predict_gaussian` gives for ``[x, g_k]`` with ``include_noise=True`` (mean,
    covariance and ``Cov[x, f]``, Eq. 29-31 and ``Q^x``), organised for speed:

    - the kernel must be one RBF term over ``x`` times a factor of ``g`` (the IDDM tensor product
      ``iddm_continuous`` or the block kernel ``iddm_discrete``); the ``x`` expectations
      ``psi1, E[grad k], psi2`` come from :mod:`hgpdm_torch.expectations`;
    - the training points are grouped by their ``g`` (U groups; padded to a common size L, with
      zero weights on the padding), and ``phi [K, U]`` holds the ``g`` factor of grid value k
      and group u. The second moments contract ``psi2`` with each group's weights, then with
      ``phi``: ``O(N^2 Dx + K U N Dx)`` per stream instead of ``O(K N^2 Dx)``.

    With ``inducing = M`` the GP is replaced by its sparse pseudo-input approximation (thesis
    Sec. 3.3.3; the deterministic training conditional, DTC): with ``A = noise K_MM + K_MN K_NM``
    the mean weights become ``A^-1 K_MN Y`` and ``K^-1`` in the variance becomes
    ``K_MM^-1 - noise A^-1``. The M pseudo-inputs are training latents paired with
    ``inducing_values`` intention values (K-means centres of the training g; all codes of a
    discrete g), so the U groups above become ``inducing_values`` groups: the work per step falls
    from ``O(N^2 Dx + K U N Dx)`` to ``O(M^2 Dx + K inducing_values M Dx)``.

    Args:
        posterior: the transition GP ``[x, g] -> x_{t+1}`` (``model.transition_posterior()``).
        values: ``[K, Dg]`` intention grid (or codes).
        dtype: computation dtype (the posterior's weights and ``K^-1`` are cast from it).
        inducing: number of pseudo-inputs M (``None``: the exact GP).
        inducing_values: number of distinct intention values among the pseudo-inputs for a
            continuous g, at most M (default ``round(sqrt(M))``, or all training values when
            ``M >= N``).
    """

    def __init__(
        self,
        posterior: GPPosterior,
        values: torch.Tensor,
        dtype: torch.dtype | None = None,
        *,
        inducing: int | None = None,
        inducing_values: int | None = None,
    ) -> None:
        dtype = dtype or posterior.train_inputs.dtype
        X = posterior.train_inputs
        dx = X.shape[1] - values.shape[1]
        leaves = kernel_leaves(posterior.kernel, X.shape[1])
        weights, kinv = posterior.weights, posterior.kinv
        if inducing is not None:
            if isinstance(inducing, bool) or not isinstance(inducing, int) or inducing < 1:
                raise ValueError(f"inducing must be a positive int or None, got {inducing!r}")
            if inducing_values is not None and (
                isinstance(inducing_values, bool)
                or not isinstance(inducing_values, int)
                or inducing_values < 1
            ):
                raise ValueError(
                    f"inducing_values must be a positive int or None, got {inducing_values!r}"
                )
            if inducing_values is not None and inducing_values > inducing:
                raise ValueError(
                    f"inducing_values ({inducing_values}) cannot exceed inducing ({inducing}): "
                    "each intention value needs at least one pseudo-input"
                )
            discrete = any(leaf.codes for leaf in leaves)
            X = _pseudo_inputs(X, dx, inducing, inducing_values, discrete)
            weights, kinv = _dtc(posterior, X)
        elif inducing_values is not None:
            raise ValueError("inducing_values needs inducing (the number of pseudo-inputs)")
        uniq, group = torch.unique(X[:, dx:], dim=0, return_inverse=True)
        terms = split_terms(leaves, torch.cat([uniq.new_zeros(len(uniq), dx), uniq], 1), values, dx)
        if len(terms) != 1 or terms[0].kind != "rbf" or terms[0].factor is None:
            raise TypeError(
                "SharedTransition needs the IDDM transition kernel (one RBF over x times a factor "
                "of g: 'iddm_continuous' or 'iddm_discrete' without sharing); got a kernel with "
                f"{[t.kind for t in terms]} terms"
            )
        (term,) = terms
        n, u_count = X.shape[0], len(uniq)
        counts = torch.bincount(group, minlength=u_count)
        size = int(counts.max())
        order = torch.argsort(group, stable=True)
        starts = torch.cumsum(counts, 0) - counts
        rank = torch.arange(n, device=X.device) - starts[group[order]]
        pad = torch.full((u_count, size), n, dtype=torch.long, device=X.device)
        pad[group[order], rank] = order
        flat = pad.reshape(-1)
        real = flat < n
        Xx = torch.cat([X[:, :dx], X.new_zeros(1, dx)])
        beta = torch.cat([weights, weights.new_zeros(1, dx)])
        kinv = torch.nn.functional.pad(kinv, (0, 1, 0, 1))
        self.values = values.to(dtype)
        self.dx, self.groups, self.group_size = dx, u_count, size
        self.inputs = Xx[flat].to(dtype)  # [U L, Dx]
        self.beta = beta[pad].to(dtype)  # [U, L, Dx]
        self.kinv = kinv[flat[:, None], flat[None, :]].to(dtype)  # [U L, U L]
        self.real = real
        self.phi = term.factor.to(dtype)  # [K, U]
        # phi_k(u_n) beta_n for every grid value k and padded point n: [K, U L, Dx]
        self.weighted_beta = (self.phi[:, :, None, None] * self.beta).reshape(len(values), -1, dx)
        self.term = Term("rbf", term.coef.detach().to(dtype), term.weight.detach().to(dtype), None)
        self.coef = self.term.coef
        if posterior.code_noise is not None:  # alpha_4,k of each intention value: [K]
            self.noise = posterior.code_noise[values[:, -1].round().long()].to(dtype)
        elif posterior.noise.dim():
            raise ValueError(
                "SharedTransition needs a scalar process noise or one per intention code "
                "(GPPosterior code_noise), got a noise per training point only"
            )
        else:
            self.noise = posterior.noise.to(dtype)

    @property
    def num_values(self) -> int:
        """K."""
        return self.phi.shape[0]

    def moments(
        self, mu: torch.Tensor, Sigma: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Moments of ``x_{t+1} = f(x, g_k) + noise`` for every k at ``x ~ N(mu, Sigma)``
        (``noise``: alpha_4, or the ``alpha_4,k`` of value k with a per-value process noise).

        Args:
            mu: ``[B, Dx]``; Sigma: ``[B, Dx, Dx]``.

        Returns:
            ``mean [B, K, Dx]``, ``cov [B, K, Dx, Dx]`` and ``Cov[x, x_{t+1}] [B, K, Dx, Dx]``.
        """
        b, dx, U, L = mu.shape[0], self.dx, self.groups, self.group_size
        p1, grad = term_psi1_grad(self.term, mu, Sigma, self.inputs)  # [B, UL], [B, Dx, UL]
        q = term_psi2(self.term, self.term, mu, Sigma, self.inputs)  # [B, UL, UL]
        phi, beta = self.phi, self.beta
        m_u = torch.einsum("bul,ula->bua", p1.view(b, U, L), beta)
        mean = torch.einsum("ku,bua->bka", phi, m_u)
        g_u = torch.einsum("bdul,ula->bdua", grad.view(b, dx, U, L), beta)
        cross = Sigma[:, None] @ torch.einsum("ku,bdua->bkda", phi, g_u)
        T = (q * self.kinv).view(b, U, L, U, L).sum(2).sum(-1)  # [B, U, U]; strided sum first
        trace = ((phi @ T) * phi).sum(-1)
        # Cov[f] = beta_k^T (psi2 - psi1 psi1^T) beta_k: centring the N x N matrix first keeps
        # float32 usable (beta is large when the noise is small) and gives the covariance
        # without the cancellation of second moment minus squared mean.
        q = torch.baddbmm(q, p1[:, :, None], p1[:, None, :], alpha=-1.0)
        # sum_uv phi_ku phi_kv beta_u^T q_uv beta_v: contract each group's weights
        # (block-sparse, O(N^2 Dx)), then phi over groups, then the rows
        P1 = beta.transpose(1, 2) @ q.view(b, U, L, U * L)  # [B, U, Dx, UL]
        P2 = (phi @ P1.reshape(b, U, dx * U * L)).view(b, -1, dx, U * L)  # [B, K, Dx, UL]
        cov = P2 @ self.weighted_beta  # [B, K, Dx, Dx]
        var = (self.coef - trace).clamp_min(0.0) + self.noise
        cov = symmetrize(cov) + torch.diag_embed(var[..., None].expand(b, -1, dx))
        return mean, cov, cross


class LinearMeasurement:
    r"""GP-ADF measurement update (Eq. 25, 32-35) for a GP with a linear kernel, precomputed.

    For ``k(x, x') = x^T diag(w) x'`` (Eq. 20, gpytorch ``LinearKernel`` optionally scaled) with
    training inputs ``X`` and weights ``beta = (K + noise I)^-1 Y``, the GP is
    ``f(x) = W^T x`` with ``W = diag(w) X^T beta`` and variance ``x^T Q x`` with
    ``Q = diag(w) - diag(w) X^T (K + noise I)^-1 X diag(w)``. At ``x ~ N(mu, P)``::

        mean = W^T mu + offset,   Cov[x, z] = P W,
        cov  = W^T P W + v diag(s^2),   v = tr(Q (P + mu mu^T)) + noise,

    exactly the moments :meth:`GPPosterior.predict_gaussian` gives (``s`` the output scale).
    The observation noise ``v diag(s^2)`` is one scalar per input times a fixed diagonal, so
    in scaled units ``z~ = (z - offset) / s`` the innovation covariance is
    ``W~^T P W~ + v I`` with ``W~ = W diag(1/s)``. With the reduced QR factorisation
    ``W~^T = U R`` (``U [Dz, k]`` orthonormal, ``R [k, Dx]``, ``k = min(Dx, Dz)``) it splits
    into ``S = R P R^T + v I`` on the span of ``U`` and ``v I`` on its complement::

        r = U^T z~ - R mu,   r_perp = z~ - U U^T z~   (independent of the latent state),
        log p(z) = -1/2 (r^T S^-1 r + |r_perp|^2 / v + log|S| + (Dz - k) log v
                         + 2 sum log s + Dz log 2 pi),
        posterior mean = mu + P R^T S^-1 r,   posterior cov = P - P R^T S^-1 R P.

    Only the ``k x k`` matrix S is factorised (never P, so a singular prediction is fine) and
    no squared norms are subtracted, which keeps float32 accurate: ``O(Dx^2 Dz)`` per input.
    The filter updates B x K Gaussians per step.

    Args:
        posterior: the measurement GP (``model.measurement_posterior()``).
        dtype: computation dtype.

    Raises:
        TypeError: when the kernel is not a single linear term.
    """

    def __init__(self, posterior: GPPosterior, dtype: torch.dtype | None = None) -> None:
        leaves = kernel_leaves(posterior.kernel, posterior.input_dim)
        if len(leaves) != 1 or leaves[0].kind != "linear" or leaves[0].codes:
            raise TypeError("LinearMeasurement needs a measurement GP with a linear kernel")
        dtype = dtype or posterior.train_inputs.dtype
        w = (leaves[0].coef * leaves[0].weight).detach().double()
        XW = posterior.train_inputs.double() * w
        W = XW.T @ posterior.weights.double()  # [Dx, Dz]
        scale = posterior.scale.double().expand(W.shape[1])
        U, R = torch.linalg.qr((W / scale).T)  # reduced: [Dz, k], [k, Dx]
        kinv = posterior.kinv.double()
        self.U, self.R = U.to(dtype), R.to(dtype)
        self.Q = symmetrize(torch.diag(w) - XW.T @ kinv @ XW).to(dtype)
        self.scale = scale.to(dtype)
        self.log_scale2 = (2.0 * scale.log().sum()).to(dtype)
        self.offset = posterior.offset.to(dtype)
        self.noise = posterior.noise.to(dtype)

    def update(
        self, mu: torch.Tensor, P: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Like :func:`~hgpdm_torch.inference.filtering.gp_adf_update` (NaN rows of ``z`` leave
        the prediction unchanged, log-likelihood 0). Shapes ``[..., Dx]``, ``[..., Dx, Dx]``,
        ``[..., Dz]`` -> ``[..., Dx]``, ``[..., Dx, Dx]``, ``[...]``."""
        U, R = self.U, self.R
        dz, k = U.shape
        second = P + mu[..., :, None] * mu[..., None, :]
        v = (self.Q * second).sum((-1, -2)) + self.noise  # [...]
        missing = torch.isnan(z).all(-1)
        zs = torch.where(missing[..., None], torch.zeros_like(z), (z - self.offset) / self.scale)
        zu = zs @ U  # [..., k]
        r_perp = zs - zu @ U.T
        r = zu - mu @ R.T
        RP = R @ P  # [..., k, Dx]
        eye = torch.eye(k, dtype=P.dtype, device=P.device)
        S = symmetrize(RP @ R.T) + v[..., None, None] * eye
        L = psd_cholesky(S, name="predicted observation covariance (latent span)")
        A = torch.linalg.solve_triangular(L, RP, upper=False)  # L^-1 R P
        a = torch.linalg.solve_triangular(L, r[..., :, None], upper=False)  # L^-1 r
        keep = missing[..., None]
        mean = torch.where(keep, mu, mu + (A.transpose(-1, -2) @ a)[..., 0])
        cov = torch.where(keep[..., None], P, symmetrize(P - A.transpose(-1, -2) @ A))
        maha = a[..., 0].pow(2).sum(-1) + r_perp.pow(2).sum(-1) / v
        logdet = cholesky_logdet(L) + (dz - k) * v.log() + self.log_scale2
        ll = log_density_terms(maha, logdet, dz)
        return mean, cov, torch.where(missing, torch.zeros_like(ll), ll)


def _measurement_update(posterior: GPPosterior, dtype: torch.dtype):
    """The fastest exact GP-ADF measurement update for this GP: ``(mu, P, z) -> (m, P, ll)``."""
    try:
        return LinearMeasurement(posterior, dtype).update
    except TypeError:
        post = _posterior_as(posterior, dtype)
        return functools.partial(gp_adf_update, post)  # picklable, unlike a lambda


# ------------------------------------------------------------------------------------------
# Algorithm 3.2: online inference
# ------------------------------------------------------------------------------------------


def _finite_state(mean: torch.Tensor, cov: torch.Tensor, log_belief: torch.Tensor) -> torch.Tensor:
    """``[B]`` mask of streams whose mean ``[B, Dx]``, covariance ``[B, Dx, Dx]`` and log belief
    ``[B, K]`` are usable: the sum of the means, the covariance entries and the largest log
    belief is finite. So no entry is NaN or +-inf (or so large, ~1e307, that the sum overflows)
    except -inf log beliefs (zero probabilities), of which not all."""
    return torch.isfinite(mean.sum(-1) + cov.sum((-2, -1)) + log_belief.amax(-1))


#: Largest rounding error of the transition moments in a filter's dtype, relative to the
#: predictive spread, that :class:`OnlineIntentionFilter` accepts for a dtype other than its
#: model's. Measured in float32: 0.03-1.2 on models whose float32 beliefs stay within 0.05 of
#: float64 without a failed stream, ~1.4e3 with alpha-bar (alpha_4 = 1e-4), whose streams fail
#: within a few updates. The check catches that breakdown; it does not promise 0.02.
PRECISION_LIMIT = 10.0


def _check_precision(model: HGPDM, reference: SharedTransition, low: SharedTransition) -> None:
    """Refuse ``low``'s dtype where its transition moments at 8 training latents, with the
    latents' covariance scaled by 1, 1e-2 and 1e-4, differ from ``reference``'s by more than
    :data:`PRECISION_LIMIT` times the smallest predictive standard deviation (means) or
    variance (covariances)."""
    x = model.latent.detach().to(reference.inputs.dtype)
    idx = torch.linspace(0, x.shape[0] - 1, min(8, x.shape[0]), device=x.device).round().long()
    _, spread = _state_prior(model, None, None, x.dtype)  # the training latents' covariance
    worst = 0.0
    for scale in (1.0, 1e-2, 1e-4):
        mu, P = x[idx], (scale * spread).expand(len(idx), -1, -1)
        m_ref, c_ref, _ = reference.moments(mu, P)
        m_low, c_low, _ = low.moments(mu.to(low.inputs.dtype), P.to(low.inputs.dtype))
        var = torch.linalg.eigvalsh(c_ref)[..., 0].clamp_min(torch.finfo(c_ref.dtype).tiny)
        err_c = (c_low.to(c_ref.dtype) - c_ref).abs().amax((-1, -2)) / var
        err_m = (m_low.to(m_ref.dtype) - m_ref).abs().amax(-1) / var.sqrt()
        worst = max(worst, float(err_c.max()), float(err_m.max()))
    if not worst <= PRECISION_LIMIT:
        name = str(low.inputs.dtype).removeprefix("torch.")
        raise ValueError(
            f"dtype={name} is not accurate enough for this model: its rounding error in the "
            f"transition moments is {worst:.3g} times the predictive spread (limit "
            f"{PRECISION_LIMIT}), because the weights (K + alpha_4 I)^-1 are too large for its "
            f"digits (process noise alpha_4 = {float(model.transition_noise):.3g}); use the "
            "model's dtype, or a model with a larger alpha_4"
        )


class OnlineIntentionFilter:
    r"""Online intention inference (Algorithm 3.2) for B independent streams at once.

    One Gaussian ``q`` over the latent state is shared by all intention values. Each
    :meth:`update` with a new observation ``z_t`` per stream predicts ``q(x_{t-1}, x_t)`` for every
    intention value from the filtered ``q(x_{t-1})`` (:class:`SharedTransition`), then updates the
    log belief ``B_t = E_t(g) + (1 - eps) B_{t-1}`` (normalised; lines 10-11) with the evidence
    ``E_t(g)`` of this step:

    - ``evidence="bound"`` (Algorithm 3.2 as printed): mix the K predictions under ``B_{t-1}``,
      moment matched (``mixing="grid"``), or moment match the transition at ``[x, g]`` with
      ``g`` Gaussian with the belief's mean and variance (``mixing="gaussian"``, Sec. 3.4.2);
      filter ``q(x_t)`` (GP-ADF, Eq. 25, 32-35); smooth ``q(x_{t-1} | z_{1:t})`` one step back
      (GP-RTSS, Eq. 26-27); ``E_t(g) = Q_{t-1}(g)`` (module docstring).
    - ``evidence="predictive"`` (default): ``E_t(g) = log q(z_t | z_{1:t-1}, g)``, the GP-ADF
      predictive likelihood of ``z_t`` under each intention from the shared ``q(x_{t-1})``; then
      ``q(x_t)`` is the moment-matched mixture of the K filtered Gaussians under ``B_t``.

    Why two: with one ``q`` shared by all g, ``Q_{t-1}(g)`` scores g as if the latent states were
    known exactly, so per step it counts evidence ``~ |f(x, g) - f(x, g')|^2 / alpha_4``; with a
    small process noise ``alpha_4`` the belief collapses after a step or two and is badly
    over-confident (``tests/inference/test_intention.py`` measures it). The predictive
    likelihood weighs the same transition difference against the state and observation
    uncertainty: it is the exact Bayes recursion of a filter that collapses ``q`` to one
    Gaussian per step, and its credible sets are calibrated when the model is right. Both
    reduce to GP-ADF/GP-RTSS for K = 1.

    The first observation of a stream initialises ``q(x_1)`` from the prior ``N(mu0, Sigma0)``
    and leaves the belief at the prior (lines 1-3). A NaN row is a prediction-only step: ``q``
    is predicted under the belief and the belief only forgets (``B_t = (1 - eps) B_{t-1}``),
    since an unobserved step carries no evidence about g; before the first observation it leaves
    the stream unstarted.

    Stream isolation: nothing one stream receives or computes changes another's belief, bit for
    bit: streams are updated in chunks that are fixed ranges of stream indices, each computing
    all its streams (unobserved and discarded where they are not due), so that not even the
    rounding of a stream's update depends on the other streams' observations, failures or
    (re)starts.

    - An observation row that is bad (:class:`~hgpdm_torch.inference.filtering.ObservationCheck`:
      +-inf, NaN in some channels only, or more than ``outlier_sd`` training standard
      deviations from the training mean in a channel) is *rejected*: that stream takes a
      prediction-only step, exactly as for a NaN row, and ``belief.rejected`` flags it;
      ``rejected_count`` counts the stream's rejections.
    - A stream whose update fails numerically (a covariance that does not factorise even with
      jitter, e.g. an indefinite state covariance; a LAPACK error; or a result that is not
      finite) or whose stored state is not finite is *restarted*: its state goes back to the
      prior (``mu0``, ``Sigma0``, the prior belief, not started), ``belief.reset_streams``
      flags it and ``reset_count`` counts it. A stream that failed during the update restarts
      with its next observation; one found with a non-finite stored state (e.g. set by hand)
      restarts with the current one. A failing chunk of streams is split in halves until the
      failing streams are found, then recomputed with them at the prior and unobserved (the
      extra work is paid only when a stream fails).
    - With ``strict=True`` both raise a ``ValueError`` naming the stream, its step and (for an
      observation) the channel instead, and the update changes no state.

    The checks are vectorised over streams: an update costs a few elementwise operations on the
    ``[B, Dz]`` observations and the ``[B, ...]`` state more than the filter itself (about 0.1 ms
    for one stream).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.IDDM` (tensor-product transition kernel).
        intentions: grid of values (continuous g, ``[K]``/``[K, Dg]``) or codes (discrete g);
            see :func:`intention_grid`.
        forgetting: ``eps`` in ``[0, 1)``, a Python or NumPy real number or a 0-dim tensor; 0
            keeps all evidence (plain Bayes recursion).
        batch_size: B, the number of independent streams.
        prior: ``[K]`` prior probabilities (default uniform).
        evidence: ``"predictive"`` or ``"bound"``.
        mixing: ``"grid"`` or ``"gaussian"`` (continuous g with ``evidence="bound"`` only).
        relinearize: (``"bound"``) score ``Q`` with the transition moment matched at the smoothed
            ``q(x_{t-1} | z_{1:t})`` (exactly DESIGN.md's formula, twice the cost) instead of
            the filtered ``q(x_{t-1} | z_{1:t-1})``. ``mixing="gaussian"`` always does.
        mu0: ``[Dx]`` mean of the first state's prior (default: the training latents' mean).
        Sigma0: ``[Dx, Dx]`` its covariance (default: the training latents' covariance).
        state_prior: ``"marginal"`` (``mu0``, ``Sigma0``) or, for a discrete g, ``"class"``:
            the first observation is scored under each value's prior ``p(x_1 | g)``
            (:func:`class_state_prior`), ``B_1(g) = log p(g) + log q(z_1 | g)``, and ``q(x_1)``
            is the moment-matched mixture of the K posteriors; see :func:`infer_intention`.
        temperature: ``T > 0``; every step's evidence counts as ``E_t(g) / T``
            (:mod:`~hgpdm_torch.inference.calibration`): 1 is the thesis's recursion, ``T > 1``
            a less confident belief (choose it with
            :func:`~hgpdm_torch.inference.calibration.fit_temperature` on held-out streams).
        dtype: computation dtype (default the model's; float32 halves memory traffic). Another
            dtype than the model's is refused (``ValueError``) where its rounding error in the
            transition moments, at training latents and three state spreads, exceeds
            :data:`PRECISION_LIMIT` times the predictive standard deviation (covariance:
            variance): typically float32 with a small process noise alpha_4, whose weights
            ``(K + alpha_4 I)^-1`` are too large for 7 digits.
        inducing: pseudo-inputs of a sparse transition GP (Sec. 3.3.3; see
            :class:`SharedTransition`), or ``None`` for the exact GP.
        inducing_values: distinct intention values among the pseudo-inputs (continuous g;
            default ``round(sqrt(inducing))``, all training values when ``inducing >= N``).
        chunk_size: positive int, streams processed together; the ``[chunk, N, N]``
            temporaries are passed over several times, so the default ``2^19 / N^2`` keeps them
            in cache.
        outlier_sd: plausibility threshold in training standard deviations per channel (default
            100; see :class:`~hgpdm_torch.inference.filtering.ObservationCheck`); ``None``
            rejects only non-finite values and partly NaN rows.
        strict: raise instead of rejecting an observation or restarting a stream.

    Attributes:
        mean, cov: ``[B, Dx]``, ``[B, Dx, Dx]`` the shared ``q(x_t)`` of every stream.
        log_belief: ``[B, K]`` normalised log posterior over the grid.
        started: ``[B]`` bool, whether the stream has seen its first observation.
        steps: ``[B]`` int64, observations (missing ones included) given to each stream since it
            was (re)started; a stream's current observation has step ``steps[b]`` in messages.
        rejected_count, reset_count: ``[B]`` int64, rejected observations and automatic restarts
            of each stream since :meth:`reset`.
        check: the :class:`~hgpdm_torch.inference.filtering.ObservationCheck` in use.

    Shapes: ``update(z [B, Dz])`` (or ``[Dz]`` when B = 1) -> :class:`IntentionBelief` with
    ``prob [B, K]`` (or ``[K]``), ``rejected [B]`` and ``reset_streams [B]`` (or ``[]``).
    """

    def __init__(
        self,
        model: HGPDM,
        intentions: Any = None,
        *,
        forgetting: float = 0.2,
        batch_size: int = 1,
        prior: Any = None,
        evidence: str = "predictive",
        mixing: str = "grid",
        relinearize: bool = False,
        mu0: Any = None,
        Sigma0: Any = None,
        state_prior: str = "marginal",
        temperature: float = 1.0,
        dtype: torch.dtype | None = None,
        inducing: int | None = None,
        inducing_values: int | None = None,
        chunk_size: int | None = None,
        outlier_sd: float | None = DEFAULT_OUTLIER_SD,
        strict: bool = False,
    ) -> None:
        values = intention_grid(model, intentions)
        eps = _real_scalar(forgetting, "forgetting (epsilon)")
        if not 0.0 <= eps < 1.0:
            raise ValueError(f"forgetting (epsilon) must be in [0, 1), got {forgetting!r}")
        if (
            isinstance(batch_size, bool)
            or not isinstance(batch_size, numbers.Integral)
            or int(batch_size) < 1
        ):
            raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
        chunk_size = _check_chunk_size(chunk_size)
        check_choice(evidence, "evidence", ("predictive", "bound"))
        check_choice(mixing, "mixing", ("grid", "gaussian"))
        if mixing == "gaussian" and (model.intention != "continuous" or evidence != "bound"):
            raise ValueError("mixing='gaussian' needs a continuous g and evidence='bound'")
        self.dtype = dtype or model.latent.dtype
        self.continuous = model.intention == "continuous"
        trans = model.transition_posterior()
        self.transition = SharedTransition(
            trans, values, self.dtype, inducing=inducing, inducing_values=inducing_values
        )
        if self.dtype != trans.train_inputs.dtype:
            reference = SharedTransition(
                trans, values, trans.train_inputs.dtype, inducing=inducing,
                inducing_values=inducing_values,
            )  # fmt: skip
            _check_precision(model, reference, self.transition)
        meas = model.measurement_posterior()
        self.check = ObservationCheck.from_measurement(meas, outlier_sd)
        self.measure = _measurement_update(meas, self.dtype)
        self.gaussian_transition = (
            _posterior_as(trans, self.dtype) if mixing == "gaussian" else None
        )
        self.values = self.transition.values
        self.log_prior = intention_log_prior(prior, len(values), self.dtype, values.device)
        check_choice(state_prior, "state_prior", STATE_PRIORS)
        self.state_prior = state_prior
        if state_prior == "class":
            self.class_mu0, self.class_Sigma0 = _first_state_prior(
                model, values, mu0, Sigma0, state_prior, self.dtype
            )
            mu0 = Sigma0 = None  # an unstarted stream stores the marginal prior
        self.mu0, self.Sigma0 = _state_prior(model, mu0, Sigma0, self.dtype)
        self.forgetting = eps
        self.temperature = check_temperature(temperature)
        self.batch_size = int(batch_size)
        self.evidence = evidence
        self.mixing, self.relinearize = mixing, bool(relinearize) or mixing == "gaussian"
        self.strict = bool(strict)
        self.obs_dim = model.obs_dim
        n = self.transition.inputs.shape[0]
        self.chunk_size = chunk_size or max(1, 2**19 // (n * n))
        self.reset()

    @property
    def num_values(self) -> int:
        """K, the number of intention values."""
        return self.values.shape[0]

    def _stream_index(self, streams: Any) -> torch.Tensor:
        """Stream indices ``[S]`` (int64, in ``[0, B)``) from indices or a ``[B]`` bool mask."""
        B = self.batch_size
        try:
            idx = torch.as_tensor(streams, device=self.mean.device)
        except (TypeError, ValueError, RuntimeError) as err:
            raise TypeError(f"streams must be stream indices or a [B] bool mask: {err}") from err
        if idx.numel() == 0:
            return idx.new_zeros(0, dtype=torch.long)
        if idx.dtype == torch.bool:
            if idx.shape != (B,):
                raise ValueError(f"a streams mask must have shape [B] = [{B}], got {idx.shape}")
            return torch.nonzero(idx).flatten()
        if idx.is_floating_point() or idx.is_complex():
            raise TypeError(f"streams must be integer indices or a bool mask, got {idx.dtype}")
        idx = idx.reshape(-1).long()
        if bool(((idx < -B) | (idx >= B)).any()):
            raise ValueError(f"streams must be indices in [-{B}, {B}), got {idx.tolist()}")
        return idx % B

    def reset(self, streams: Any = None) -> None:
        """Restart streams at the prior and zero their ``steps``, ``rejected_count`` and
        ``reset_count``.

        Args:
            streams: ``None`` (all streams), stream indices (an int or a sequence/tensor of
                ints, negative ones counting from the end) or a ``[B]`` bool mask. An empty
                selection is a no-op.
        """
        if streams is None:
            B, dx, K = self.batch_size, self.mu0.shape[0], self.num_values
            like = self.mu0  # the state lives on the model's device, in the filter's dtype
            self.mean = like.new_empty(B, dx, dtype=self.dtype)
            self.cov = like.new_empty(B, dx, dx, dtype=self.dtype)
            self.log_belief = like.new_empty(B, K, dtype=self.dtype)
            self.started = like.new_zeros(B, dtype=torch.bool)
            self.steps = like.new_zeros(B, dtype=torch.long)
            self.rejected_count = like.new_zeros(B, dtype=torch.long)
            self.reset_count = like.new_zeros(B, dtype=torch.long)
            idx: Any = slice(None)
        else:
            idx = self._stream_index(streams)
            if idx.numel() == 0:
                return
        self.mean[idx] = self.mu0
        self.cov[idx] = self.Sigma0
        self.log_belief[idx] = self.log_prior
        self.started[idx] = False
        self.steps[idx] = 0
        self.rejected_count[idx] = 0
        self.reset_count[idx] = 0

    def belief(self) -> IntentionBelief:
        """The current posterior over intentions, ``prob [B, K]`` (no ``rejected`` flags)."""
        return IntentionBelief.from_log(self.log_belief, self.values, self.continuous)

    def update(self, z: Any) -> IntentionBelief:
        """Process one observation per stream (Algorithm 3.2, lines 5-11).

        Args:
            z: ``[B, Dz]`` observations (``[Dz]`` when B = 1); a NaN row is a missing
                observation of that stream. A bad row (inf, partly NaN, or implausible; see
                the class docstring) is rejected for its stream only (``strict``: raises).

        Returns:
            The posterior after this step: ``prob [B, K]`` (``[K]`` for a ``[Dz]`` input), for a
            continuous g its ``mean`` and ``std``, and the flags ``rejected`` and
            ``reset_streams`` ``[B]`` (``[]``).

        Raises:
            ValueError: a wrong shape; with ``strict``, a bad observation or a failed stream
                (naming the stream, step and channel); the filter's state is then unchanged.
        """
        z = _check_observations(z, self.obs_dim, min_ndim=1)
        single = z.dim() == 1
        if single:
            z = z[None]
        B = self.batch_size
        if z.shape != (B, self.obs_dim):
            raise ValueError(
                f"z must have shape [B, Dz] = [{self.batch_size}, {self.obs_dim}], got "
                f"{tuple(z.shape)}"
            )
        _, rejected = self.check.classify(z)
        any_rejected = bool(rejected.any())
        if any_rejected:
            b = int(torch.nonzero(rejected)[0])
            if self.strict:
                raise _bad_observation(self._where(b), self.check.reason(z[b]))
            z = z.masked_fill(rejected[:, None], math.nan)
        z = z.to(self.mean.device, self.dtype)
        # the update works on copies, written back at the end: a strict error changes nothing
        mean, cov, log_belief = self.mean.clone(), self.cov.clone(), self.log_belief.clone()
        started = self.started.clone()
        broken = ~_finite_state(mean, cov, log_belief)
        any_broken = bool(broken.any())
        if any_broken:
            self._fail(int(torch.nonzero(broken)[0]), "holds a non-finite state")
            self._restart(broken, mean, cov, log_belief, started)
        failed = torch.zeros_like(broken)
        new = ~started
        num_new = int(new.sum())
        # Chunks are fixed ranges of streams and compute every stream of their range, the
        # inactive ones unobserved and discarded: the shapes, and so the rounding, of a stream's
        # update do not depend on which other streams are new, rejected or failing. The step
        # runs first: it reads the state of the new streams before they are initialised.
        for fn, active, size, targets, count in (
            (self._step, ~new, self.chunk_size, (mean, cov, log_belief), B - num_new),
            (self._initialise, new, _INIT_CHUNK, (mean, cov, log_belief), num_new),
        ):
            if count == 0:
                continue
            every = count == B
            inputs = (
                mean,
                cov,
                log_belief,
                z if every else z.masked_fill(~active[:, None], math.nan),
            )
            for start in range(0, B, size):
                rows = slice(start, start + size)
                act = active[rows]
                if not every and not bool(act.any()):
                    continue
                out = self._guarded(fn, rows, inputs, act, failed)
                for target, value in zip(targets, out, strict=True):
                    if not every:
                        keep = act.view(-1, *([1] * (value.dim() - 1)))
                        value = torch.where(keep, value, target[rows])
                    target[rows] = value
        if num_new:
            started |= new & ~torch.isnan(z).all(-1)
        failed |= ~_finite_state(mean, cov, log_belief)
        any_failed = bool(failed.any())
        if any_failed:
            self._fail(int(torch.nonzero(failed)[0]), "gave a non-finite state")
            self._restart(failed, mean, cov, log_belief, started)
        for attr, value in (
            ("mean", mean), ("cov", cov), ("log_belief", log_belief), ("started", started),
        ):  # fmt: skip
            getattr(self, attr).copy_(value)
        self.steps += 1
        reset = broken | failed
        if any_broken or any_failed:
            # a stream restarted before its step counts this observation, one that failed not
            self.steps.copy_(torch.where(broken, 1, self.steps).masked_fill_(failed, 0))
            self.reset_count += reset
        if any_rejected:
            self.rejected_count += rejected
        if single:
            out = IntentionBelief.from_log(self.log_belief[0], self.values, self.continuous)
            out.rejected, out.reset_streams = rejected[0], reset[0]
        else:
            out = self.belief()
            out.rejected, out.reset_streams = rejected, reset
        return out

    def _where(self, b: int) -> str:
        return f"z[{b}] (stream {b}, step {int(self.steps[b])})"

    def _fail(self, b: int, what: str, err: Exception | None = None) -> None:
        """With ``strict``, raise for stream ``b`` (else the caller restarts it)."""
        if self.strict:
            cause = f": {err}" if err is not None else ""
            raise ValueError(
                f"stream {b} at step {int(self.steps[b])} {what}{cause} (with strict=False it "
                "would be restarted at the prior)"
            ) from err

    def _guarded(
        self,
        fn: Callable[..., tuple[torch.Tensor, ...]],
        rows: slice,
        inputs: tuple[torch.Tensor, ...],
        active: torch.Tensor,
        failed: torch.Tensor,
    ) -> tuple[torch.Tensor, ...]:
        """``fn`` on the streams ``rows`` of ``inputs`` (``mean, cov, log_belief, z``, ``[B, ..]``).

        Where it fails numerically (``_NUMERICAL_ERRORS``), bisection finds the streams that fail
        on their own; the active ones among them are marked in ``failed [B]`` (``strict``:
        raised), and ``fn`` is run again on all ``rows`` with those streams at the prior and
        unobserved, so that the others get the results (bit for bit) they get without them.
        """
        args = tuple(x[rows] for x in inputs)
        try:
            return fn(*args)
        except _NUMERICAL_ERRORS as err:
            error = err
        pos = torch.arange(len(active), device=active.device)
        bad = self._bisect(fn, args, pos, active, rows.start, error)
        if len(bad) == 0:  # no stream fails on its own: not a failure of a stream
            raise error
        failed[rows.start + bad[active[bad]]] = True
        args = tuple(a.clone() for a in args)
        for a, prior in zip(args, (self.mu0, self.Sigma0, self.log_prior, math.nan), strict=True):
            a[bad] = prior
        return fn(*args)

    def _bisect(
        self,
        fn: Callable[..., tuple[torch.Tensor, ...]],
        args: tuple[torch.Tensor, ...],
        pos: torch.Tensor,
        active: torch.Tensor,
        offset: int,
        error: Exception | None = None,
    ) -> torch.Tensor:
        """The positions among ``pos`` at which ``fn`` fails on a single stream (``error``:
        how ``fn`` already failed on all of ``pos``)."""
        if error is None:
            try:
                fn(*(a[pos] for a in args))
                return pos[:0]
            except _NUMERICAL_ERRORS as err:
                error = err
        if len(pos) == 1:
            if bool(active[pos[0]]):
                self._fail(offset + int(pos[0]), "failed numerically", error)
            return pos
        half = len(pos) // 2
        first = self._bisect(fn, args, pos[:half], active, offset)
        return torch.cat([first, self._bisect(fn, args, pos[half:], active, offset)])

    def _restart(
        self,
        streams: torch.Tensor,
        mean: torch.Tensor,
        cov: torch.Tensor,
        log_belief: torch.Tensor,
        started: torch.Tensor,
    ) -> None:
        """Put the ``[B]`` mask ``streams`` of the given state tensors back at the prior."""
        mean[streams] = self.mu0
        cov[streams] = self.Sigma0
        log_belief[streams] = self.log_prior
        started[streams] = False

    @settings.internal_step()  # the prior was checked when set
    def _initialise(
        self, m: torch.Tensor, P: torch.Tensor, log_belief: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Algorithm 3.2, lines 1-3: ``q(x_1)`` from the prior and ``z_1``; the belief stays
        (``state_prior="class"``: the belief takes ``log q(z_1 | g)``, ``q(x_1)`` the mixture)."""
        if self.state_prior == "marginal":
            mean, cov, _ = self.measure(m, P, z)
            return mean, cov, log_belief
        B, K = z.shape[0], self.num_values
        mk = self.class_mu0.expand(B, K, -1)
        Pk = self.class_Sigma0.expand(B, K, -1, -1)
        mean, cov, ll = self.measure(mk, Pk, z[:, None, :].expand(-1, K, -1))
        new = log_belief + ll / self.temperature
        new = new - torch.logsumexp(new, -1, keepdim=True)
        mean, cov = mixture_moments(new.exp(), mean, cov)
        return mean, cov, new

    @settings.internal_step()  # the state is the filter's own; finiteness is checked in update
    def _step(
        self, m: torch.Tensor, P: torch.Tensor, log_belief: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        observed = ~torch.isnan(z).all(-1)
        if self.evidence == "predictive":
            mf, Pf, evidence = self._predictive_step(m, P, z)
        else:
            mf, Pf, evidence = self._bound_step(m, P, log_belief, z)
        new = (1.0 - self.forgetting) * log_belief
        evidence = evidence / self.temperature
        new = new + torch.where(observed[:, None], evidence, torch.zeros_like(evidence))
        new = new - torch.logsumexp(new, -1, keepdim=True)
        if self.evidence == "predictive":
            mf, Pf = mixture_moments(new.exp(), mf, Pf)
        return mf, Pf, new

    def _predictive_step(
        self, m: torch.Tensor, P: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-intention GP-ADF update: filtered ``[B, K, Dx(, Dx)]`` and ``log q(z_t | g)``."""
        mean, cov, _ = self.transition.moments(m, P)
        K = mean.shape[1]
        zk = z[:, None, :].expand(-1, K, -1)
        return self.measure(mean, cov, zk)

    def _bound_step(
        self, m: torch.Tensor, P: torch.Tensor, log_belief: torch.Tensor, z: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Algorithm 3.2, lines 6-9: shared filtered ``q(x_t)`` and ``Q_{t-1}(g) [B, K]``."""
        prob = log_belief.exp()
        if self.gaussian_transition is None:
            per_k = self.transition.moments(m, P)
            mp, Pp, C = mixture_moments(prob, *per_k)
        else:
            mp, Pp, C = self._gaussian_prediction(prob, m, P)
        mf, Pf, _ = self.measure(mp, Pp, z)
        # one-step GP-RTSS (Eq. 26-27); Cs = Cov[x_{t-1}, x_t | z_{1:t}]
        ms, Ps, Cs = rts_step(m, P, mp, Pp, C, mf, Pf, name="prediction")
        m_lin, P_lin = m, P
        if self.relinearize:
            m_lin, P_lin = ms, Ps
            per_k = self.transition.moments(ms, Ps)
        Q = expected_log_conditional(
            m_lin[:, None], P_lin[:, None], *per_k,
            ms[:, None], Ps[:, None], mf[:, None], Pf[:, None], Cs[:, None],
        )  # fmt: skip
        return mf, Pf, Q

    def _gaussian_prediction(
        self, prob: torch.Tensor, m: torch.Tensor, P: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Transition moment matched at ``[x, g]`` with ``g ~ N(mean, var)`` of the belief."""
        mu, Sigma = independent_joint(m, P, *mixture_moments(prob, self.values))
        dx = m.shape[-1]
        mean, cov, io = self.gaussian_transition.predict_gaussian(
            mu, symmetrize(Sigma), include_noise=True
        )
        return mean, cov, io[..., :dx, :]


# ------------------------------------------------------------------------------------------
# Algorithm 3.1: batch inference
# ------------------------------------------------------------------------------------------


def batch_bound_terms(
    trans: GPPosterior,
    meas: GPPosterior,
    z: torch.Tensor,
    g: torch.Tensor,
    mu0: torch.Tensor,
    Sigma0: torch.Tensor,
    *,
    outlier_sd: float | None = DEFAULT_OUTLIER_SD,
) -> dict[str, torch.Tensor]:
    """The four terms of the bound of Eq. 22 (without ``log p(g)``), each ``[K, W]``.

    ``"state"``: ``E_q[log p(x_1)]``; ``"measurement"``: ``sum_t E_q[log p(z_t | x_t)]``;
    ``"transition"``: ``sum_t Q_t(g)``; ``"entropy"``: ``H(q)``, with ``q = q_g(x_{1:T})`` the
    GP-RTSS smoother under ``g``. Their sum is :func:`batch_bound`. Comparing a term across the
    K values shows where the evidence for (or against) each value comes from: on real gestures
    only ``"transition"`` and ``"state"`` favour the true class (README, action recognition).
    Arguments as :func:`batch_bound`.
    """
    gk = g[:, None, :]  # [K, 1, Dg] broadcasts against the W windows
    fr = filter_sequence(trans, meas, z, mu0, Sigma0, g=gk, outlier_sd=outlier_sd)
    sm = smooth(fr)  # [K, W, T, ...]
    shape = (len(g), z.shape[0])
    q1_chol = psd_cholesky(sm.cov[..., 0, :, :], name="smoothed covariance")
    h = entropy(q1_chol).expand(shape)
    L0 = psd_cholesky(Sigma0, name="prior covariance")
    state = expected_log_density(sm.mean[..., 0, :], q1_chol, mu0, L0)
    # E_q[log p(z_t | x_t)] over observed steps
    with settings.internal_step():  # the smoother's own marginals
        zm, zc, zx = meas.predict_gaussian(sm.mean, sm.cov, include_noise=True)
    observed = ~torch.isnan(z).all(-1)
    zz = torch.where(observed[..., None], z, zm)
    lz = expected_log_conditional(sm.mean, sm.cov, zm, zc, zx, sm.mean, sm.cov, zz, None, None)
    measurement = torch.where(observed, lz, torch.zeros_like(lz)).sum(-1)
    transition = torch.zeros_like(measurement)
    if z.shape[-2] > 1:
        m_in, P_in = sm.mean[..., :-1, :], sm.cov[..., :-1, :, :]
        with settings.internal_step():
            pm, pc, px = trans.predict_gaussian(
                m_in, P_in, g=g[:, None, None, :], include_noise=True
            )
        Q = expected_log_conditional(
            m_in, P_in, pm, pc, px, m_in, P_in,
            sm.mean[..., 1:, :], sm.cov[..., 1:, :, :], sm.cross_cov,
        )  # fmt: skip
        # Markov entropy: H = H(x_1) + sum_t [H(x_t, x_{t+1}) - H(x_t)]
        pair = torch.cat(
            [
                torch.cat([P_in, sm.cross_cov], -1),
                torch.cat([sm.cross_cov.transpose(-1, -2), sm.cov[..., 1:, :, :]], -1),
            ],
            -2,
        )
        H = _entropy(symmetrize(pair)) - _entropy(P_in)
        transition = Q.sum(-1)
        h = h + H.sum(-1)
    return {
        "state": state.expand(shape),
        "measurement": measurement.expand(shape),
        "transition": transition.expand(shape),
        "entropy": h,
    }


def batch_bound(
    trans: GPPosterior,
    meas: GPPosterior,
    z: torch.Tensor,
    g: torch.Tensor,
    mu0: torch.Tensor,
    Sigma0: torch.Tensor,
    *,
    outlier_sd: float | None = DEFAULT_OUTLIER_SD,
) -> torch.Tensor:
    """The bound of Eq. 22 without ``log p(g)``, for every intention value and window.

    ``B(g) - log p(g) = E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q)``
    with ``q = q_g(x_{1:T})`` the GP-RTSS smoother under ``g`` (the sum of
    :func:`batch_bound_terms`). For a linear-Gaussian model the smoother is exact and the bound
    equals ``log p(z_{1:T} | g)``.

    Args:
        trans: transition GP ``[x, g] -> x_{t+1}``; meas: measurement GP ``x -> z``.
        z: ``[W, T, Dz]`` windows (NaN rows missing; other bad rows raise, see
            :func:`~hgpdm_torch.inference.filtering.filter_sequence`).
        g: ``[K, Dg]`` intention values (codes).
        mu0: ``[Dx]`` mean of the first state's prior (or ``[K, 1, Dx]``: one per intention
            value).
        Sigma0: ``[Dx, Dx]`` its covariance (or ``[K, 1, Dx, Dx]``).
        outlier_sd: plausibility threshold of the observation check (``None``: finiteness only).

    Returns:
        ``[K, W]``.
    """
    terms = batch_bound_terms(trans, meas, z, g, mu0, Sigma0, outlier_sd=outlier_sd)
    return sum(terms.values())


def infer_intention(
    model: HGPDM,
    z: Any,
    intentions: Any = None,
    *,
    window: int | None = None,
    prior: Any = None,
    mu0: Any = None,
    Sigma0: Any = None,
    state_prior: str = "marginal",
    temperature: float = 1.0,
    chunk_size: int | None = None,
    outlier_sd: float | None = DEFAULT_OUTLIER_SD,
    progress: bool = False,
) -> IntentionBelief:
    r"""Batch intention inference (Algorithm 3.1), batched over the K intention values.

    For every value ``g_k`` the GP-ADF/RTSS smoother (:mod:`hgpdm_torch.inference.filtering`)
    gives ``q_k(x_{1:T}) ~= p(x_{1:T} | z_{1:T}, g_k)`` (Eq. 23-28); the bound of Eq. 22,
    ``B(g) = log p(g) + E_q[log p(x_1)] + sum_t E_q[log p(z_t | x_t)] + sum_t Q_t(g) + H(q)``
    (``Q_t`` and the measurement term by statistical linearisation, see
    :func:`expected_log_conditional`; ``H`` the entropy of the Markov Gaussian ``q``), is
    normalised over the grid (line 4).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.HGPDM` / ``IDDM``.
        z: ``[T, Dz]`` or ``[W, T, Dz]`` observations; NaN rows are missing. A bad row (inf,
            partly NaN, or more than ``outlier_sd`` training standard deviations from the
            training mean in a channel; see
            :class:`~hgpdm_torch.inference.filtering.ObservationCheck`) raises a ``ValueError``
            naming its window, step and channel.
        intentions: grid or codes, see :func:`intention_grid`.
        window: if given, a sliding window: the belief at every step ``t`` from
            ``z_{max(1, t-window+1):t}`` (output ``[..., T, K]``).
        prior: ``[K]`` prior probabilities (default uniform).
        mu0: ``[Dx]`` mean of the prior of each window's first state (default: the training
            latents' empirical mean, as a window may start anywhere in a movement).
        Sigma0: ``[Dx, Dx]`` its covariance (default: the training latents' empirical one).
        state_prior: ``"marginal"`` (the prior above, shared by all g) or, for a discrete g,
            ``"class"``: ``p(x_1 | g)`` from the training latents of each value
            (:func:`class_state_prior`), so that where a window's movement is, not only how it
            moves, is evidence about g. On real gestures (MSRC-12) ``"class"`` recognises far
            better (README, action recognition).
        temperature: ``T > 0``: the posterior is ``p(g) exp(B'(g) / T)`` normalised, with
            ``B'`` the bound without ``log p(g)`` (:mod:`~hgpdm_torch.inference.calibration`);
            1 is Algorithm 3.1. A uniform prior keeps the ranking (and the decisions); ``T``
            chosen by :func:`~hgpdm_torch.inference.calibration.fit_temperature` on held-out
            windows calibrates the credible sets.
        chunk_size: positive int, windows processed together; default ``2^24 / (K N^2)``
            bounds the ``[K, chunk, N, N]`` moment-matching temporaries to about 128 MB each
            (float64).
        outlier_sd: plausibility threshold (limits from the model's training observations);
            ``None`` refuses only non-finite values and partly NaN rows.
        progress: show a tqdm bar over chunks.

    Returns:
        :class:`IntentionBelief` with ``prob [..., K]`` (``[..., T, K]`` with ``window``).
    """
    values = intention_grid(model, intentions)
    dtype = values.dtype
    z = _check_observations(z, model.obs_dim, min_ndim=2)
    if z.shape[-2] == 0:
        raise ValueError("z must hold at least one time step")
    if window is not None and (not isinstance(window, int) or window < 1):
        raise ValueError(f"window must be a positive int or None, got {window!r}")
    chunk_size = _check_chunk_size(chunk_size)
    temperature = check_temperature(temperature)
    trans, meas = model.transition_posterior(), model.measurement_posterior()
    found = ObservationCheck.from_measurement(meas, outlier_sd).first_bad(z)
    if found is not None:
        index, why = found
        windows = ", ".join(map(str, index[:-1]))
        where = f"window {windows}, step {index[-1]}" if windows else f"step {index[-1]}"
        raise _bad_observation(f"z{list(index)} ({where})", why)
    z = z.to(dtype)
    log_prior = intention_log_prior(prior, len(values), dtype, values.device)
    m0, S0 = _first_state_prior(model, values, mu0, Sigma0, state_prior, dtype)
    if state_prior == "class":  # [K, 1, ...] broadcasts against the windows in batch_bound
        m0, S0 = m0[:, None], S0[:, None]
    n = trans.train_inputs.shape[0]
    chunk_size = chunk_size or max(1, 2**24 // (len(values) * n * n))
    lead, T = z.shape[:-2], z.shape[-2]
    flat = z.reshape(-1, T, z.shape[-1])
    # one batch of equal-length windows per length: w for t >= w, then the shorter first ones
    if window is None:
        jobs = [(flat, None)]
    else:
        w = min(window, T)
        full = flat.unfold(1, w, 1).transpose(-1, -2)  # [F, T - w + 1, w, Dz]
        jobs = [(full.reshape(-1, w, z.shape[-1]), ("full", w))]
        jobs += [(flat[:, :t], ("start", t)) for t in range(1, w)]
    out = values.new_empty(flat.shape[0], T if window else 1, len(values))
    for batch, tag in tqdm(jobs, disable=not progress, desc="batch intention", leave=False):
        parts = [
            batch_bound(
                trans, meas, batch[i : i + chunk_size], values, m0, S0, outlier_sd=outlier_sd
            ).mT
            for i in range(0, batch.shape[0], chunk_size)
        ]
        score = torch.cat(parts, 0) / temperature + log_prior  # [windows, K]
        if tag is None:
            out[:, 0] = score
        elif tag[0] == "full":
            out[:, tag[1] - 1 :] = score.view(flat.shape[0], -1, len(values))
        else:
            out[:, tag[1] - 1] = score
    shape = (*lead, T, len(values)) if window else (*lead, len(values))
    return IntentionBelief.from_log(out.reshape(shape), values, model.intention == "continuous")
