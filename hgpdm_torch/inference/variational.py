r"""Variational Bayes inference of the exogenous variable and the latent states of a new window
(thesis Sec. 2.3, Algorithm 2.2, App. 2.A-2.B).

Given a fitted :class:`~hgpdm_torch.models.GPDM` / :class:`~hgpdm_torch.models.HGPDM` (its MAP
training latents define a measurement GP ``h`` and a transition GP ``f``) and a window of
observations ``z_{1:T}``, the mean-field family (Eq. 11)

    q(x_{1:T}) = prod_t N(x_t | mu_t, Sigma_t)        [and q(g) = N(mu_g, Sigma_g), Sec. 2.3.3]

is fitted by maximising the negative free energy of Eq. 13 under the FIC factorisation (Eq. 8-9):

    F(q, g) = sum_t E_q[log p(z_t | x_t)] + sum_t E_q[log p(x_{t+1} | x_t, g)]
              - H(q(x_1), p(x_1)) + H(q)     [+ E_q[log p(g)] + H(q(g)) for a continuous g]

Approximations (Eq. 15-17, kept as in the thesis; DESIGN.md sec. 7): the GP predictive variances
``sigma_z^2(x_t)`` and ``sigma_x^2(x_t, g)`` are evaluated at the variational mean ``mu_t`` (they
still depend on ``mu_t`` and carry its gradient). Each expected log likelihood then needs only
``E_q[||y - m(x)||^2] = ||y - psi1 beta||^2 + sum_d (beta_d^T psi2 beta_d - (psi1 beta_d)^2)``
(+ ``tr Sigma_{t+1}`` for a Gaussian target ``y = x_{t+1}``), with the kernel expectations
``psi0, psi1, psi2`` of :mod:`hgpdm_torch.expectations` (App. 2.A's ``l``, ``Q``, ``R``).

Algorithm 2.2 runs for all K values of a discrete g in one batched optimisation: the variational
parameters carry a ``K`` axis and every window and candidate is its own problem. q starts from
a mean-field Laplace approximation (Levenberg-Marquardt to the MAP states, then ``Sigma_t`` the
inverse diagonal blocks of the Gauss-Newton precision), which is the optimum of F to second
order; optional L-BFGS steps on the exact F polish it. (L-BFGS alone from a GP-RTSS start stalls
hundreds of nats below the optimum with alpha-bar's process noise 1e-4: that made recognition
fail.)
A discrete g's transition kernel is block-diagonal, so each value touches only its own training
points (``GPPosterior``'s per-code blocks).

Missing observations (Sec. 2.3.2): a row of NaN in the window drops ``E_q[log p(z_t | x_t)]``.
A row with some but not all entries NaN is rejected (partial observations are not modelled).

Prediction (Sec. 2.3.2, App. 2.B): :meth:`VariationalInference.observation_joint` builds the
Gaussian ``q(z_{1:T})`` with cross-time covariances ``scale_d^2 (E[k(x_s, x_t)] - l_s^T K^-1 l_t)``
and :func:`condition_gaussian` conditions it on the observed rows (forecasting, gap recovery).

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim, ``Dz`` observation
dim, ``Dg`` dim of a continuous g; ``...`` leading batch dims (e.g. windows).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import constraints
from pyro.nn import PyroModule, PyroParam
from tqdm.auto import trange

from ..expectations import (
    kernel_leaves,
    leaves_psi0,
    split_terms,
    term_k,
    term_psi1,
    term_psi2,
)
from ..gaussian import (
    condition_gaussian,
    entropy,
    expected_log_density,
    independent_joint,
    log_density,
    log_density_terms,
)
from ..gp import GPPosterior
from ..linalg import CholeskyError, psd_cholesky, symmetrize
from ..models import GPDM, HGPDM
from ..validation import as_tensor, check_choice
from .filtering import filter_sequence, smooth
from .residual import ar1_residual_forecast

__all__ = [
    "MeanFieldGuide",
    "batched_lbfgs",
    "VBResult",
    "VariationalInference",
    "condition_gaussian",
    "window_mask",
]

_PRUNE_SAFETY = 3.0  # optimism factor of the LM pruning rule (see _map_states)
_PRUNE_MAX_DAMPING = 1.0  # LM damping up to which the pruning rule trusts the step's gain
_ROW_BLOCK_BYTES = 2**26  # per-row GP blocks up to this size, else one code at a time


# --------------------------------------------------------------------------------------------
# The variational family (Eq. 11 and Sec. 2.3.3) as a Pyro guide
# --------------------------------------------------------------------------------------------


class MeanFieldGuide(PyroModule):
    r"""Mean-field Gaussian guide ``q(x_{1:T}) [q(g)]`` (Eq. 11; Sec. 2.3.3).

    Parameters are :class:`pyro.nn.PyroParam` s: ``loc [..., T, Dx]`` and ``scale_tril
    [..., T, Dx, Dx]`` under ``constraints.lower_cholesky`` (so every ``Sigma_t = L_t L_t^T`` is
    positive definite), and optionally ``g_loc [..., Dg]``, ``g_scale_tril [..., Dg, Dg]``.

    Calling the guide samples the sites ``"x"`` (event shape ``[T, Dx]``) and ``"g"``, so it can be
    used with ``pyro.infer`` (e.g. ``Trace_ELBO`` against :meth:`VariationalInference.pyro_model`);
    :meth:`VariationalInference.free_energy` evaluates the same objective in closed form.
    With Pyro's global parameter store, clear it (``pyro.clear_param_store()``) before using a new
    guide in ``pyro.infer``: guides share parameter names.

    Args:
        loc: ``[..., T, Dx]`` initial means.
        cov: ``[..., T, Dx, Dx]`` initial covariances.
        g_loc: ``[..., Dg]`` initial mean of a continuous g, or ``None``.
        g_cov: ``[..., Dg, Dg]`` its initial covariance.
    """

    def __init__(
        self,
        loc: torch.Tensor,
        cov: torch.Tensor,
        g_loc: torch.Tensor | None = None,
        g_cov: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        loc = as_tensor(loc, "loc", min_ndim=2)
        cov = as_tensor(cov, "cov", min_ndim=3, dtype=loc.dtype)
        if cov.shape != (*loc.shape, loc.shape[-1]):
            raise ValueError(
                f"cov must have shape {(*loc.shape, loc.shape[-1])} to match loc, "
                f"got {tuple(cov.shape)}"
            )
        self.loc = PyroParam(loc.detach().clone())
        self.scale_tril = PyroParam(
            psd_cholesky(symmetrize(cov.detach()), name="initial covariance of q(x)"),
            constraint=constraints.lower_cholesky,
        )
        self.has_g = g_loc is not None
        if self.has_g:
            g_loc = as_tensor(g_loc, "g_loc", min_ndim=1, dtype=loc.dtype)
            if g_cov is None:
                raise ValueError("g_cov is required with g_loc")
            g_cov = as_tensor(g_cov, "g_cov", min_ndim=2, dtype=loc.dtype)
            self.g_loc = PyroParam(g_loc.detach().clone())
            self.g_scale_tril = PyroParam(
                psd_cholesky(symmetrize(g_cov.detach()), name="initial covariance of q(g)"),
                constraint=constraints.lower_cholesky,
            )

    @property
    def cov(self) -> torch.Tensor:
        """``[..., T, Dx, Dx]`` covariances ``Sigma_t``."""
        L = self.scale_tril
        return L @ L.transpose(-1, -2)

    @property
    def g_cov(self) -> torch.Tensor:
        """``[..., Dg, Dg]`` covariance of q(g)."""
        L = self.g_scale_tril
        return L @ L.transpose(-1, -2)

    def entropy(self) -> torch.Tensor:
        """``H(q)`` ``[...]``: ``sum_t 1/2 log|2 pi e Sigma_t|`` (+ the entropy of q(g))."""
        h = entropy(self.scale_tril).sum(-1)
        return h + entropy(self.g_scale_tril) if self.has_g else h

    def forward(self, *args: object, **kwargs: object) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """Sample ``x [..., T, Dx]`` (site ``"x"``) and, with a continuous g, ``g [..., 1, Dg]``.

        The arguments of the model (``pyro.infer`` passes them to the guide too) are ignored.
        """
        loc, tril = self.loc, self.scale_tril
        # windows and candidates of g are independent: one plate per batch dim
        with pyro.plate_stack("vb_batch", loc.shape[:-2]):
            x = pyro.sample("x", dist.MultivariateNormal(loc, scale_tril=tril).to_event(1))
            if not self.has_g:
                return x
            # batch [..., 1]: g aligned with the candidate axis K (= 1) of "x"
            qg = dist.MultivariateNormal(
                self.g_loc[..., None, :], scale_tril=self.g_scale_tril[..., None, :, :]
            )
            return x, pyro.sample("g", qg)


# --------------------------------------------------------------------------------------------
# Expected squared error of a GP mean under a Gaussian input (App. 2.A terms (a)-(d))
# --------------------------------------------------------------------------------------------


class _GaussianInputGP:
    """A GP posterior in the form the free energy needs: all input columns Gaussian.

    ``X [..., N, D]``, ``beta [..., N, Dout]``, ``kinv [..., N, N]`` and a 0/1 ``mask [..., N]``
    (padding of per-code blocks), where ``...`` broadcasts against the inputs' batch dims.
    """

    def __init__(self, post: GPPosterior, codes: torch.Tensor | None = None) -> None:
        self.post = post
        with torch.no_grad():
            leaves = kernel_leaves(post.kernel, post.input_dim)
        if codes is None:
            self.X, self.beta, self.kinv, self.mask = (
                post.train_inputs,
                post.weights,
                post.kinv,
                None,
            )
            self.leaves = leaves
        elif post.blocks() is not None:
            # Block-diagonal K_x of a discrete g: code c reads only its own block (exact).
            X, beta, kinv, mask = (b[codes] for b in post.blocks())
            d = X.shape[-1] - 1
            self.X, self.beta, self.kinv, self.mask = X[..., :d], beta, kinv, mask
            self.leaves = [replace(lf, weight=lf.weight[:d], codes=()) for lf in leaves]
        else:
            # A discrete g in a kernel that is not block-diagonal (shared dynamics): every code
            # reads all training points; the code only sets the terms' per-point factors.
            d = post.input_dim - 1
            self.X, self.beta, self.kinv, self.mask = (
                post.train_inputs[..., :d],
                post.weights,
                post.kinv,
                None,
            )
            g = codes[..., None].to(post.train_inputs.dtype)
            self.terms = split_terms(leaves, post.train_inputs, g, d)
            # k(x, x) at equal codes: delta(g, g) = 1
            self.leaves = [replace(lf, weight=lf.weight[:d], codes=()) for lf in leaves]
            self.dim = d
            return
        self.dim = self.X.shape[-1]
        self.terms = [
            t if self.mask is None else replace(t, factor=self.mask)
            for t in split_terms(self.leaves, self.X, None, self.dim)
        ]

    def expected_kernel(
        self, mu: torch.Tensor, Sigma: torch.Tensor, X: torch.Tensor
    ) -> torch.Tensor:
        """``E[k(x, X_i)]`` ``[..., N]`` at ``x ~ N(mu, Sigma)`` for any points ``X [..., N, D]``.

        Only for a GP without per-point factors (the measurement GP).
        """
        return sum(term_psi1(t, mu, Sigma, X) for t in self.terms)

    def predict_point(
        self, mu: torch.Tensor, *, jacobian: bool = False
    ) -> tuple[torch.Tensor, ...]:
        """Centred predictive mean ``[..., Dout]`` and variance ``[...]`` at points ``mu``.

        The variance ``k(mu, mu) - k(mu, X) K^-1 k(X, mu) + noise`` is the plug-in of Eq. 15 / 17
        (unscaled; multiply by ``scale^2`` per output). Differentiable in ``mu``. With
        ``jacobian=True`` also returns ``d mean / d mu`` ``[..., Dout, D]``, from the kernel
        gradients of :func:`~hgpdm_torch.expectations.term_k`.
        """
        k, dk = 0.0, 0.0
        for t in self.terms:
            p, gr = term_k(t, mu, self.X, grad=jacobian)
            if jacobian:
                dk = dk + (gr if t.factor is None else t.factor[..., None, :] * gr)
            k = k + (p if t.factor is None else t.factor * p)
        quad = ((k[..., None, :] @ self.kinv)[..., 0, :] * k).sum(-1)
        kxx = leaves_psi0(self.leaves, mu, torch.zeros_like(mu).diag_embed(), None)
        mean = (k[..., None, :] @ self.beta)[..., 0, :]
        var = (kxx - quad).clamp_min(0.0) + self.post.noise
        if not jacobian:
            return mean, var
        return mean, var, (dk @ self.beta).transpose(-1, -2)

    def var_at_mean(self, mu: torch.Tensor) -> torch.Tensor:
        """Plug-in predictive variance at ``mu`` (Eq. 15 / 17), ``[...]``."""
        return self.predict_point(mu)[1]

    def mean_moments(
        self, mu: torch.Tensor, Sigma: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``E[m_d(x)]`` and ``E[m_d(x)^2]`` of the centred GP mean, each ``[..., Dout]``.

        ``E[m] = psi1 beta`` and ``E[m_d^2] = beta_d^T psi2 beta_d`` summed over kernel terms and
        term pairs (App. 2.A terms (a)-(d)).
        """
        fbeta = [
            self.beta if t.factor is None else t.factor[..., None] * self.beta for t in self.terms
        ]
        mean, second = 0.0, 0.0
        for i, (a, fa) in enumerate(zip(self.terms, fbeta, strict=True)):
            p1 = term_psi1(a, mu, Sigma, self.X)
            mean = mean + (p1[..., None, :] @ fa)[..., 0, :]
            for j in range(i, len(self.terms)):
                q = term_psi2(a, self.terms[j], mu, Sigma, self.X)
                s = ((q @ fbeta[j]) * fa).sum(-2)
                second = second + (2.0 * s if j > i else s)  # pair (j, i) is the transpose
        return mean, second


def _sq_error(
    y: torch.Tensor, y_var: torch.Tensor | None, mean: torch.Tensor, second: torch.Tensor
) -> torch.Tensor:
    """``E[(y_d - m_d)^2]`` per dim for independent ``y`` (mean y, variances y_var) and m."""
    err = y.pow(2) - 2.0 * y * mean + second
    return err if y_var is None else err + y_var


def _tril_free(cov: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(d, M)`` with ``chol(cov) = diag(e^d) (I + strictly lower M)``."""
    L = psd_cholesky(symmetrize(cov), name="covariance of q")
    diag = L.diagonal(dim1=-2, dim2=-1)
    return diag.log(), torch.tril(L / diag[..., :, None], -1)


def _tril_from_free(d: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """Lower Cholesky factor ``diag(e^d) (I + strictly lower M)``: scale-free off-diagonals."""
    eye = torch.eye(d.shape[-1], dtype=d.dtype, device=d.device)
    return d.exp()[..., :, None] * (eye + torch.tril(M, -1))


# --------------------------------------------------------------------------------------------
# Results
# --------------------------------------------------------------------------------------------


@dataclass
class VBResult:
    """Output of :meth:`VariationalInference.infer` (Algorithm 2.2).

    Attributes:
        values: ``[K]`` candidate values of g (codes of a discrete g; empty for a GPDM or a
            continuous g, where ``K = 1``).
        log_evidence: ``[..., K]`` maximised ``F(q, g)``, the approximate ``log p(z_{1:T} | g)``.
        posterior: ``[..., K]`` ``p(g | z_{1:T})`` from ``log_evidence`` and the prior over g.
        g_ml: ``[...]`` index into ``values`` of the largest ``log_evidence`` (the ML value).
        mean: ``[..., K, T, Dx]`` means of q(x) per candidate g.
        cov: ``[..., K, T, Dx, Dx]`` covariances of q(x).
        g_mean: ``[..., Dg]`` mean of q(g) (continuous g), else ``None``.
        g_cov: ``[..., Dg, Dg]`` covariance of q(g), else ``None``.
        guide: the fitted :class:`MeanFieldGuide`.
        history: ``-sum F`` over all windows and candidates after each optimiser iteration.
    """

    values: torch.Tensor
    log_evidence: torch.Tensor
    posterior: torch.Tensor
    g_ml: torch.Tensor
    mean: torch.Tensor
    cov: torch.Tensor
    g_mean: torch.Tensor | None
    g_cov: torch.Tensor | None
    guide: MeanFieldGuide
    history: list[float]

    def ml_state(self) -> tuple[torch.Tensor, torch.Tensor]:
        """q(x) of the ML value of g: ``mean [..., T, Dx]`` and ``cov [..., T, Dx, Dx]``."""
        return self.select(self.g_ml)

    def select(self, index: torch.Tensor | int) -> tuple[torch.Tensor, torch.Tensor]:
        """q(x) for candidate ``index`` (``[...]`` or an int): mean ``[..., T, Dx]``, cov."""
        index = torch.as_tensor(index, device=self.mean.device).expand(self.mean.shape[:-3])
        i = index[..., None, None, None]
        T, D = self.mean.shape[-2:]
        mean = self.mean.gather(-3, i.expand(*index.shape, 1, T, D))[..., 0, :, :]
        cov = self.cov.gather(-4, i[..., None].expand(*index.shape, 1, T, D, D))
        return mean, cov[..., 0, :, :, :]


# --------------------------------------------------------------------------------------------
# Inference
# --------------------------------------------------------------------------------------------


def window_mask(z: object, obs_dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a window ``z [..., T, Dz]`` whose NaN rows are missing observations.

    Returns:
        ``z`` (float) and the ``[..., T]`` boolean mask of observed rows.

    Raises:
        ValueError: ``T < 2``, wrong ``Dz``, partially missing rows, or a window without any
            observed row.
    """
    z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
    if z.shape[-1] != obs_dim:
        raise ValueError(f"z must have Dz = {obs_dim} columns (the model's), got {z.shape[-1]}")
    if z.shape[-2] < 2:
        raise ValueError(f"z must be a window of at least 2 time steps, got {z.shape[-2]}")
    nan = torch.isnan(z)
    missing = nan.all(-1)
    if bool((nan.any(-1) & ~missing).any()):
        raise ValueError(
            "z rows must be fully observed or fully NaN (missing); partially observed rows are "
            "not supported"
        )
    observed = ~missing
    if bool((~observed.any(-1)).any()):
        raise ValueError("z has a window in which every row is missing (all NaN)")
    return z, observed


def _gaussian_argument(
    pair: object, name: str, dim: int, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a ``(mean [dim], cov [dim, dim])`` pair given by the user."""
    if not isinstance(pair, tuple | list) or len(pair) != 2:
        raise TypeError(f"{name} must be a (mean, cov) pair, got {type(pair).__name__}")
    mean = as_tensor(pair[0], f"{name} mean", ndim=1, dtype=dtype)
    cov = as_tensor(pair[1], f"{name} cov", ndim=2, dtype=dtype)
    if mean.shape != (dim,) or cov.shape != (dim, dim):
        raise ValueError(f"{name} must be (mean [{dim}], cov [{dim}, {dim}])")
    return mean, cov


class VariationalInference:
    """Variational Bayes inference in a fitted GPDM / H-GPDM (Sec. 2.3, Algorithm 2.2).

    Args:
        model: a fitted :class:`~hgpdm_torch.models.GPDM` (no g), or an
            :class:`~hgpdm_torch.models.HGPDM` / ``IDDM`` with a discrete or continuous g.
        x1_prior: ``(mean [Dx], cov [Dx, Dx])`` of ``p(x_1)``, the first state of a window. The
            default is the Gaussian fitted to all training latents, since a window may start
            anywhere in a movement (the thesis's ``N(m_1, S_1)``).
        g_prior: for a discrete g, ``[K]`` prior probabilities (default uniform); for a continuous
            g, ``(mean [Dg], cov [Dg, Dg])`` (default: fitted to the training intentions).

    Example:
        >>> vb = VariationalInference(model)                   # doctest: +SKIP
        >>> res = vb.infer(window)                             # doctest: +SKIP
        >>> res.posterior, res.g_ml                            # doctest: +SKIP
    """

    def __init__(
        self,
        model: GPDM,
        *,
        x1_prior: tuple[object, object] | None = None,
        g_prior: object = None,
    ) -> None:
        if not isinstance(model, GPDM):
            raise TypeError(f"model must be a GPDM/HGPDM, got {type(model).__name__}")
        self.model = model
        self.kind = model.intention if isinstance(model, HGPDM) else "none"
        self.measurement = model.measurement_posterior()
        self.transition = model.transition_posterior()
        if self.transition.noise.dim() != 0:
            raise ValueError(
                "variational inference needs one shared process noise; this model has a noise "
                "per intention value (noise_per_value=True): use infer_intention or "
                "OnlineIntentionFilter, or a model with noise_per_value=False"
            )
        self.latent_dim = model.latent_dim
        self.obs_dim = model.obs_dim
        dtype = self.measurement.train_inputs.dtype
        self._h = _GaussianInputGP(self.measurement)
        lat = model.latent.detach()
        if x1_prior is None:
            m1 = lat.mean(0)
            S1 = torch.cov(lat.T).reshape(self.latent_dim, self.latent_dim)
            S1 = S1 + 1e-6 * torch.eye(self.latent_dim, dtype=dtype)
        else:
            m1, S1 = _gaussian_argument(x1_prior, "x1_prior", self.latent_dim, dtype)
        self.x1_mean, self.x1_cov = m1, symmetrize(S1)
        self._x1_chol = psd_cholesky(self.x1_cov, name="x1_prior covariance")
        self.g_dim = 0
        if self.kind == "discrete":
            K = model.num_values
            self.values = torch.arange(K)
            prior = torch.full((K,), 1.0 / K, dtype=dtype) if g_prior is None else g_prior
            prior = as_tensor(prior, "g_prior", ndim=1, dtype=dtype)
            if (
                prior.shape != (K,)
                or bool((prior <= 0).any())
                or abs(float(prior.sum()) - 1) > 1e-6
            ):
                # a zero prior would give -inf evidence (and NaN posteriors): drop that value from
                # the candidates instead
                raise ValueError(f"g_prior must be [{K}] positive probabilities summing to 1")
            self.log_g_prior = prior.log()
        else:
            self.values = torch.zeros(0, dtype=torch.long)
            self.log_g_prior = torch.zeros(1, dtype=dtype)
            self._f = _GaussianInputGP(self.transition)
        if self.kind == "continuous":
            g = model.intentions
            self.g_dim = g.shape[1]
            if g_prior is None:
                mg = g.mean(0)
                Sg = torch.cov(g.T).reshape(self.g_dim, self.g_dim) if g.shape[0] > 1 else None
                if Sg is None or bool((Sg.diagonal() <= 0).any()):
                    Sg = torch.eye(self.g_dim, dtype=dtype)
            else:
                mg, Sg = _gaussian_argument(g_prior, "g_prior", self.g_dim, dtype)
            self.g_prior_mean, self.g_prior_cov = mg, symmetrize(Sg)
            self._g_chol = psd_cholesky(self.g_prior_cov, name="g_prior covariance")

    # ------------------------------------------------------------------ candidates of g
    def _candidates(self, values: object) -> torch.Tensor:
        if self.kind != "discrete":
            if values is not None:
                raise ValueError(f"values applies to a discrete g only (model has {self.kind!r})")
            return self.values
        if values is None:
            return self.values
        v = torch.as_tensor(values)
        if v.is_floating_point():
            if not bool((v == v.round()).all()):
                raise ValueError("values must be integer codes of g")
            v = v.long()
        if v.dim() == 0:
            v = v[None]
        if bool(((v < 0) | (v >= self.model.num_values)).any()):
            raise ValueError(f"values must be codes in [0, {self.model.num_values - 1}]")
        return v

    def _transition_gp(self, values: torch.Tensor) -> _GaussianInputGP:
        if self.kind != "discrete":
            return self._f
        # [..., K] codes -> blocks [..., K, 1, N, .] (the 1 is the time axis); kept per set of
        # codes, since the optimisers ask for the same candidates (or one code) at every step
        cache = self.__dict__.setdefault("_f_cache", {})
        key = (tuple(values.shape), tuple(values.flatten().tolist()), values.device)
        if key not in cache:
            if len(cache) > 64:
                cache.clear()
            cache[key] = _GaussianInputGP(self.transition, values[..., None])
        return cache[key]

    # ------------------------------------------------------------------ the free energy
    def free_energy(
        self,
        z: object,
        loc: torch.Tensor,
        scale_tril: torch.Tensor,
        *,
        values: object = None,
        g_loc: torch.Tensor | None = None,
        g_scale_tril: torch.Tensor | None = None,
    ) -> torch.Tensor:
        r"""Negative free energy ``F(q, g)`` of Eq. 13 with Eq. 15-17, in closed form.

        Args:
            z: ``[..., T, Dz]`` window; NaN rows are missing (their measurement term is dropped).
            loc: ``[..., K, T, Dx]`` means of q(x), one set per candidate g.
            scale_tril: ``[..., K, T, Dx, Dx]`` lower Cholesky factors of the covariances.
            values: ``[K]`` (or ``[..., K]``) candidate codes of a discrete g (default all K).
            g_loc: ``[..., Dg]`` mean of q(g) of a continuous g.
            g_scale_tril: ``[..., Dg, Dg]`` Cholesky factor of the covariance of q(g).

        Returns:
            ``[..., K]`` F for each candidate (``K = 1`` without a discrete g).
        """
        z, observed = window_mask(z, self.obs_dim)
        return self._free_energy(
            z, observed, loc, scale_tril, self._candidates(values), g_loc, g_scale_tril
        )

    def _free_energy(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        loc: torch.Tensor,
        scale_tril: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None,
        g_scale_tril: torch.Tensor | None,
    ) -> torch.Tensor:
        if loc.shape[-2:] != (z.shape[-2], self.latent_dim):
            raise ValueError(
                f"loc must have trailing shape [K, {z.shape[-2]}, {self.latent_dim}], "
                f"got {tuple(loc.shape)}"
            )
        if (self.kind == "continuous") != (g_loc is not None):
            raise ValueError("q(g) (g_loc, g_scale_tril) is required exactly for a continuous g")
        cov = scale_tril @ scale_tril.transpose(-1, -2)
        h = self.measurement
        # Eq. 16: measurement terms of the observed rows
        zc = (torch.nan_to_num(z) - h.offset)[..., None, :, :]  # [..., 1, T, Dz]
        var = self._h.var_at_mean(loc)[..., None] * h.scale.pow(2)  # [..., K, T, Dz]
        m, m2 = self._h.mean_moments(loc, cov)
        ll_z = log_density_terms(_sq_error(zc, None, m, m2) / var, torch.log(var), 1).sum(-1)
        ll_z = (ll_z * observed[..., None, :].to(ll_z.dtype)).sum(-1)
        # Eq. 17: transitions x_t -> x_{t+1} (with q(g) appended to the input if continuous)
        mu_in, cov_in = loc[..., :-1, :], cov[..., :-1, :, :]
        if g_loc is not None:
            mu_in, cov_in = self._append_g(mu_in, cov_in, g_loc, g_scale_tril)
        f = self._transition_gp(values)
        s2 = f.var_at_mean(mu_in)  # [..., K, T-1]
        m, m2 = f.mean_moments(mu_in, cov_in)
        nxt_var = cov[..., 1:, :, :].diagonal(dim1=-2, dim2=-1)
        err = _sq_error(loc[..., 1:, :], nxt_var, m, m2).sum(-1)
        dx = self.latent_dim
        ll_x = log_density_terms(err / s2, dx * torch.log(s2), dx).sum(-1)
        # the first state's expected log prior (minus a cross-entropy) and the entropy of q
        x1 = loc[..., 0, :], scale_tril[..., 0, :, :]
        l1 = expected_log_density(*x1, self.x1_mean, self._x1_chol)
        F = ll_z + ll_x + l1 + entropy(scale_tril).sum(-1)
        if g_loc is not None:
            lg = expected_log_density(g_loc, g_scale_tril, self.g_prior_mean, self._g_chol)
            F = F + (entropy(g_scale_tril) + lg)[..., None]
        return F

    @staticmethod
    def _append_g(
        mu: torch.Tensor, cov: torch.Tensor, g_loc: torch.Tensor, g_scale_tril: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Input ``[x_t, g]`` under ``q(x_t) q(g)``: means ``[..., K, T, Dx + Dg]``, block cov."""
        g_cov = g_scale_tril @ g_scale_tril.transpose(-1, -2)
        return independent_joint(mu, cov, g_loc[..., None, None, :], g_cov[..., None, None, :, :])

    def guide_free_energy(
        self, z: object, guide: MeanFieldGuide, *, values: object = None
    ) -> torch.Tensor:
        """:meth:`free_energy` of a :class:`MeanFieldGuide` ``[..., K]``."""
        g_loc = guide.g_loc if guide.has_g else None
        g_tril = guide.g_scale_tril if guide.has_g else None
        return self.free_energy(
            z, guide.loc, guide.scale_tril, values=values, g_loc=g_loc, g_scale_tril=g_tril
        )

    # ------------------------------------------------------------------ Pyro model of F
    def pyro_model(self, z: object, guide: MeanFieldGuide, *, values: object = None) -> None:
        r"""Pyro model whose ELBO against ``guide`` is the objective of :meth:`free_energy`.

        Latent site ``"x"`` ``[..., K, T, Dx]`` (improper flat base, its density added by
        ``pyro.factor``): ``log N(x_1 | m_1, S_1) + sum_t log N(x_{t+1} | m_x(x_t, g),
        sigma_x^2(mu_t, g) I)``, and observed site ``"z"`` with ``N(m_z(x_t), sigma_z^2(mu_t))``;
        the variances are the plug-ins of Eq. 15-17 at the guide's means (read from ``guide``).
        GP means are evaluated at the sampled states (no kernel expectations), so a Monte-Carlo
        ELBO of this model is an independent check of the closed form.
        """
        z, observed = window_mask(z, self.obs_dim)
        values = self._candidates(values)
        loc = guide.loc.detach()  # shapes only; the plug-in variances use guide.loc below
        lead = loc.shape[:-2]
        with pyro.plate_stack("vb_batch", lead):
            self._pyro_model_body(z, observed, guide, values, lead)

    def _pyro_model_body(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        guide: MeanFieldGuide,
        values: torch.Tensor,
        lead: torch.Size,
    ) -> None:
        T, dx = z.shape[-2], self.latent_dim
        x = pyro.sample("x", dist.ImproperUniform(constraints.real, lead, (T, dx)))
        mu = guide.loc
        h, f = self._h, self._transition_gp(values)
        scale2 = self.measurement.scale.pow(2)
        var_z = h.var_at_mean(mu)[..., None] * scale2  # plug-ins at the means [..., K, T, Dz]
        m_z = h.predict_point(x)[0] + self.measurement.offset
        inputs, plug = x[..., :-1, :], mu[..., :-1, :]
        if self.kind == "continuous":
            prior_g = dist.MultivariateNormal(self.g_prior_mean, scale_tril=self._g_chol)
            g = pyro.sample("g", prior_g.expand(lead))  # [..., 1, Dg], like the guide's
            gx = g[..., None, :].expand(*inputs.shape[:-1], self.g_dim)
            inputs = torch.cat([inputs, gx], -1)
            gm = guide.g_loc[..., None, None, :].expand(*plug.shape[:-1], self.g_dim)
            plug = torch.cat([plug, gm], -1)
        m_x = f.predict_point(inputs)[0]
        var_x = f.var_at_mean(plug)[..., None]
        log_p = dist.Normal(m_x, var_x.sqrt()).log_prob(x[..., 1:, :]).sum((-1, -2))
        log_p = log_p + dist.MultivariateNormal(self.x1_mean, scale_tril=self._x1_chol).log_prob(
            x[..., 0, :]
        )
        pyro.factor("latent_dynamics", log_p)
        zc = torch.nan_to_num(z)[..., None, :, :].expand(m_z.shape)
        mask = observed[..., None, :, None].expand(m_z.shape)
        lik = dist.Normal(m_z, var_z.sqrt()).mask(mask).to_event(2)
        pyro.sample("z", lik, obs=zc)

    # ------------------------------------------------------------------ Algorithm 2.2
    def initial_guess(
        self, z: torch.Tensor, values: torch.Tensor, init: str = "nearest"
    ) -> tuple[torch.Tensor, ...]:
        """Initial q(x) [and q(g)] for :meth:`infer` (Algorithm 2.2, step 1).

        ``"nearest"``: each observed row takes the latent state of the nearest training frame
        (in the model's scaled observation units) among the frames of candidate g, so every g
        starts on its own part of the latent space; missing rows follow the transition mean of
        g from the previous state (rows before the first observation copy its state).
        Covariances ``S_1 / 100`` (the Laplace step of :meth:`infer` replaces them).
        ``"filter"``: the forward sweep of Sec. 2.4.2, done by GP-ADF moment matching
        (:func:`~hgpdm_torch.inference.filtering.filter_sequence`): ``q(x_t)`` from
        ``z_{1:t}`` only, so a missing row is filled by the learned transition model of each g.
        ``"smoother"``: the GP-RTSS smoothed marginals. ``"prior"``: ``p(x_1)`` at every step.
        A continuous g starts at its prior (``"filter"``/``"smoother"``: at the filter's belief).

        Returns:
            ``loc [..., K, T, Dx]``, ``cov [..., K, T, Dx, Dx]``, and ``g_loc [..., Dg]``,
            ``g_cov [..., Dg, Dg]`` (``None`` unless g is continuous).
        """
        check_choice(init, "init", ("nearest", "filter", "smoother", "prior"))
        T, dx = z.shape[-2], self.latent_dim
        K = max(int(values.shape[-1]), 1) if self.kind == "discrete" else 1
        batch = (*z.shape[:-2], K)
        g_loc = g_cov = None
        if self.kind == "continuous":
            g_loc = self.g_prior_mean.expand(*z.shape[:-2], self.g_dim).clone()
            g_cov = self.g_prior_cov.expand(*g_loc.shape, self.g_dim).clone()
        if init == "prior":
            loc = self.x1_mean.expand(*batch, T, dx).clone()
            cov = self.x1_cov.expand(*batch, T, dx, dx).clone()
            return loc, cov, g_loc, g_cov
        if init == "nearest":
            loc = self._nearest_states(z, values, g_loc)
            return loc, (0.01 * self.x1_cov).expand(*batch, T, dx, dx).clone(), g_loc, g_cov
        g = g_cov = None
        if self.kind == "discrete":
            g = values.to(z.dtype)[..., None]  # [..., K, 1] codes
        elif self.kind == "continuous":
            g, g_cov = self.g_prior_mean, self.g_prior_cov
        with torch.no_grad():
            res = filter_sequence(
                self.transition,
                self.measurement,
                z[..., None, :, :],
                self.x1_mean,
                self.x1_cov,
                g=g,
                g_cov=g_cov,
            )
            mean, cov = res.mean, res.cov
            if init == "smoother":
                sm = smooth(res)
                mean, cov = sm.mean, sm.cov
        mean = mean.expand(*batch, *mean.shape[-2:])
        cov = cov.expand(*batch, *cov.shape[-3:])
        loc, xcov = mean[..., :dx], cov[..., :dx, :dx]
        if self.kind != "continuous":
            return loc, xcov, None, None
        return loc, xcov, mean[..., 0, -1, dx:], cov[..., 0, -1, dx:, dx:]

    def _nearest_states(
        self, z: torch.Tensor, values: torch.Tensor, g_loc: torch.Tensor | None
    ) -> torch.Tensor:
        """States ``[..., K, T, Dx]`` of the ``"nearest"`` initialisation."""
        model = self.model
        w = model.scales.detach()
        train = model.observations * w  # [M, Dz]
        rows = torch.nan_to_num(z) * w
        d2 = (rows.pow(2).sum(-1)[..., None] - 2.0 * rows @ train.T) + train.pow(2).sum(-1)
        d2 = d2[..., None, :, :]  # [..., 1, T, M]
        if self.kind == "discrete":
            seq = torch.repeat_interleave(torch.arange(model.num_sequences), model.lengths)
            code = model.intention_codes()[seq].to(values.device)  # [M]
            other = code != values[..., :, None, None]  # [..., K, 1, M]
            d2 = d2.masked_fill(other, math.inf)
        lat = model.latent.detach()
        x = lat[d2.argmin(-1)]  # [..., K, T, Dx]
        observed = ~torch.isnan(z).all(-1)  # [..., T]
        if bool(observed.all()):
            return x
        f = self._transition_gp(values)
        first = observed.to(torch.long).argmax(-1)  # first observed row
        x0 = x.gather(-2, first[..., None, None, None].expand(*x.shape[:-2], 1, x.shape[-1]))
        states = []
        for t in range(z.shape[-2]):
            obs_t = observed[..., t, None, None]
            if t == 0:
                states.append(torch.where(obs_t, x[..., 0, :], x0[..., 0, :]))
                continue
            m, _ = f.predict_point(self._transition_inputs(states[-1][..., None, :], g_loc))
            before = (first >= t)[..., None, None]  # rows before the first observation
            fill = torch.where(before, x0[..., 0, :], m[..., 0, :])
            states.append(torch.where(obs_t, x[..., t, :], fill))
        return torch.stack(states, -2)

    def _whiten(
        self,
        f: _GaussianInputGP,
        loc: torch.Tensor,
        cov: torch.Tensor,
        g_loc: torch.Tensor | None,
        g_cov: torch.Tensor | None,
    ) -> list[torch.Tensor]:
        """Free variables of the optimiser for q (inverse of :meth:`_unwhiten`)."""
        eps = []
        for t in range(loc.shape[-2] - 1):
            m, v = self._step(f, loc[..., t, :], g_loc)
            eps.append((loc[..., t + 1, :] - m) / v.sqrt())
        free = [loc[..., 0, :], torch.stack(eps, -2), *_tril_free(cov)]
        return free if g_loc is None else [*free, g_loc, *_tril_free(g_cov)]

    def _unwhiten(
        self, f: _GaussianInputGP, free: list[torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """``loc``, ``scale_tril`` (and q(g)) from the optimiser's free variables.

        The means are written as a transition rollout plus whitened innovations,
        ``mu_{t+1} = m_x(mu_t, g) + sigma_x(mu_t, g) eps_{t+1}``, so the stiff transition term of
        Eq. 17 (``sigma_x^2 ~ alpha_4``) becomes ``~ ||eps||^2 / 2``: the same F, well scaled
        for L-BFGS. Cholesky factors are ``diag(e^d) (I + strictly lower M)``.
        """
        a1, eps, d, M = free[:4]
        g_loc = g_tril = None
        if len(free) > 4:
            g_loc, g_tril = free[4], _tril_from_free(free[5], free[6])
        mus = [a1]
        for t in range(eps.shape[-2]):
            m, v = self._step(f, mus[-1], g_loc)
            mus.append(m + v.sqrt() * eps[..., t, :])
        return torch.stack(mus, -2), _tril_from_free(d, M), g_loc, g_tril

    def _step(
        self, f: _GaussianInputGP, x: torch.Tensor, g_loc: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Transition mean ``[..., K, Dx]`` and plug-in std variance ``[..., K, 1]`` at ``x``."""
        inp = x[..., None, :]  # the time axis of the transition blocks
        if g_loc is not None:
            inp = torch.cat([inp, g_loc[..., None, None, :].expand(*inp.shape[:-1], -1)], -1)
        m, v = f.predict_point(inp)
        return m[..., 0, :], v

    # ------------------------------------------------------------------ MAP states + Laplace
    def _transition_inputs(self, x: torch.Tensor, g_loc: torch.Tensor | None) -> torch.Tensor:
        """Transition inputs ``[x_t, g]`` for states ``x [..., K, S, Dx]`` (g: q(g)'s mean)."""
        if g_loc is None:
            return x
        return torch.cat([x, g_loc[..., None, None, :].expand(*x.shape[:-1], -1)], -1)

    def _log_joint(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        x: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """FIC log joint ``log p(x_{1:T}, z_obs | g)`` ``[..., K]`` of states ``x [..., K, T, Dx]``.

        ``log N(x_1 | m_1, S_1) + sum_t log N(x_{t+1} | m_x, sigma_x^2 I) + sum_{t obs}
        log N(z_t | m_z, sigma_z^2 diag(scale^2))`` with the GP predictive variances at the
        states (Eq. 8-9): the MAP objective, and the point version of Eq. 13's expectations.
        """
        h = self.measurement
        m, v = self._h.predict_point(x)
        var = v[..., None] * h.scale.pow(2)
        r = (torch.nan_to_num(z) - h.offset)[..., None, :, :] - m
        lz = log_density_terms(r.pow(2) / var, torch.log(var), 1).sum(-1)
        lz = (lz * observed[..., None, :].to(lz.dtype)).sum(-1)
        inp = self._transition_inputs(x[..., :-1, :], g_loc)
        mx, vx = self._transition_gp(values).predict_point(inp)
        dx = self.latent_dim
        err = (x[..., 1:, :] - mx).pow(2).sum(-1)
        lx = log_density_terms(err / vx, dx * torch.log(vx), dx).sum(-1)
        return lz + lx + log_density(x[..., 0, :], self.x1_mean, self._x1_chol)

    def _precision_blocks(
        self,
        observed: torch.Tensor,
        x: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Gauss-Newton precision ``J^T J`` of the log joint at states ``x [..., K, T, Dx]``.

        The residuals are whitened by the GP predictive std at ``x``; their Jacobians come from
        the GP mean's Jacobian (:meth:`_GaussianInputGP.predict_point`). The precision is
        block-tridiagonal in time.

        Returns:
            diagonal blocks ``[..., K, T, Dx, Dx]`` and blocks ``(t, t+1)`` ``[..., K, T-1, Dx,
            Dx]``.
        """
        dx = self.latent_dim
        _, vh, Jh = self._h.predict_point(x, jacobian=True)  # Jh [..., K, T, Dz, Dx]
        w = observed[..., None, :, None].to(x.dtype) / (vh[..., None] * self.measurement.scale**2)
        diag = Jh.transpose(-1, -2) @ (w[..., None] * Jh)
        inp = self._transition_inputs(x[..., :-1, :], g_loc)
        _, vf, Jf = self._transition_gp(values).predict_point(inp, jacobian=True)
        Jf = Jf[..., :dx]  # d m_x / d x_t  [..., K, T-1, Dx, Dx]
        inv = (1.0 / vf)[..., None, None]
        eye = torch.eye(dx, dtype=x.dtype, device=x.device)
        pad = torch.zeros_like(diag[..., :1, :, :])
        diag = diag + torch.cat([Jf.transpose(-1, -2) @ Jf * inv, pad], -3)
        diag = diag + torch.cat([pad, eye * inv], -3)
        prior = torch.cholesky_inverse(self._x1_chol)
        diag = diag + torch.cat([prior.expand_as(pad), torch.zeros_like(diag[..., 1:, :, :])], -3)
        return diag, -Jf.transpose(-1, -2) * inv

    @staticmethod
    def _dense(diag: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
        """Dense ``[..., T Dx, T Dx]`` matrix from tridiagonal blocks (time-major)."""
        T, dx = diag.shape[-3], diag.shape[-1]
        full = diag.new_zeros(*diag.shape[:-3], T, T, dx, dx)
        i = torch.arange(T, device=diag.device)
        full[..., i, i, :, :] = diag
        full[..., i[:-1], i[1:], :, :] = off
        full[..., i[1:], i[:-1], :, :] = off.transpose(-1, -2)
        return full.transpose(-3, -2).reshape(*diag.shape[:-3], T * dx, T * dx)

    def _map_states(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        x: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None,
        *,
        max_iter: int,
        tol: float = 1e-3,
        prune: float | None = None,
    ) -> tuple[torch.Tensor, list[float]]:
        """Maximise the log joint over ``x [..., K, T, Dx]`` by Levenberg-Marquardt.

        Each window and candidate g is its own problem: the step solves ``(J^T J + lambda
        diag(J^T J)) s = -grad`` with the exact gradient (autograd, so the ``log sigma^2(x)``
        terms are included) and its own damping ``lambda``, which shrinks after an accepted step
        and grows after a rejected one. A problem stops when an accepted step gains less than
        ``tol`` nats (far below the differences between candidates of g that matter), or, with
        ``prune`` (a heuristic), when even an optimistic value, its negative log joint minus
        three times the next step's first-order gain ``-grad^T s``, trails the best candidate of
        its window by more than ``prune`` nats while the damping is moderate (``lambda <= 1``:
        the damped step's gain is then within about ``1 + lambda`` of the Gauss-Newton step's,
        which the factor 3 covers): a candidate far from its optimum has a large predicted gain
        and is kept. Only the problems still running are computed at each iteration.

        Returns:
            The maximisers and the summed negative log joint after each iteration.
        """
        if prune is not None and not (isinstance(prune, int | float) and prune > 0):
            raise ValueError(f"prune must be a positive number of nats or None, got {prune!r}")
        batch = torch.broadcast_shapes(z.shape[:-2], observed.shape[:-1], x.shape[:-3])
        if g_loc is not None:
            batch = torch.broadcast_shapes(batch, g_loc.shape[:-1])
        K, T, dx = x.shape[-3:]
        lead = (*batch, K)
        n = math.prod(lead)
        # one row per (window, candidate) problem; K = 1 per row so that the log joint's
        # broadcasting over candidates is unchanged
        zf = z.expand(*batch, *z.shape[-2:])[..., None, :, :].expand(*lead, *z.shape[-2:])
        zf = zf.reshape(n, *z.shape[-2:])
        of = observed.expand(*batch, T)[..., None, :].expand(*lead, T).reshape(n, T)
        discrete = self.kind == "discrete"
        vf = values.to(x.device).expand(*lead).reshape(n) if discrete else values
        gf = None
        if g_loc is not None:
            gf = g_loc.expand(*batch, g_loc.shape[-1])[..., None, :].expand(*lead, -1)
            gf = gf.reshape(n, -1)

        # per-row codes copy each row's GP block (``M^2`` per row); beyond _ROW_BLOCK_BYTES the
        # rows of one code are computed together on its shared block instead
        if discrete:
            blocks = self.transition.blocks()
            # without blocks (shared dynamics) a row holds only its codes' factors
            kinv_block = self.transition.kinv[None] if blocks is None else blocks[2]
            row_bytes = kinv_block[0].numel() * kinv_block.element_size()

        def by_code(idx: torch.Tensor, fn) -> tuple[torch.Tensor, ...]:
            """``fn(rows, z, observed, values, g)`` on the rows ``idx``, results in their order."""
            gi = None if gf is None else gf[idx]
            if not discrete:
                return fn(idx, zf[idx], of[idx], vf, gi)
            if len(idx) * row_bytes <= _ROW_BLOCK_BYTES:
                return fn(idx, zf[idx], of[idx], vf[idx, None], gi)
            codes, parts, order = vf[idx], [], []
            for c in torch.unique(codes):
                sel = idx[codes == c]
                g_sel = None if gf is None else gf[sel]
                parts.append(fn(sel, zf[sel], of[sel], c.reshape(1), g_sel))
                order.append(sel)
            perm = torch.argsort(torch.cat(order))
            return tuple(torch.cat(p, 0)[perm] for p in zip(*parts, strict=True))

        def value_grad(xs: torch.Tensor):
            def fn(sel, zi, oi, vi, gi):
                xi = xs[sel].detach().requires_grad_(True)
                with torch.enable_grad():
                    v = -self._log_joint(zi, oi, xi, vi, gi)
                    (grad,) = torch.autograd.grad(v.sum(), xi)
                return v.detach()[:, 0], grad

            return fn

        def precision(xs: torch.Tensor):
            def fn(sel, zi, oi, vi, gi):
                with torch.no_grad():
                    return (self._dense(*self._precision_blocks(oi, xs[sel], vi, gi))[:, 0],)

            return fn

        x = x.expand(*lead, T, dx).reshape(n, 1, T, dx).detach().clone()
        every = torch.arange(n, device=x.device)
        f, g = by_code(every, value_grad(x))
        lam = torch.full_like(f, 1e-3)
        active = torch.isfinite(f)
        history = [float(f.sum())]
        for _ in range(max_iter):
            idx = torch.nonzero(active).flatten()
            if idx.numel() == 0:
                break
            (A,) = by_code(idx, precision(x))
            grad = g[idx].reshape(-1, T * dx, 1)
            with torch.no_grad():
                damped = A + lam[idx, None, None] * torch.diag_embed(A.diagonal(dim1=-2, dim2=-1))
                L = psd_cholesky(damped, name="Gauss-Newton matrix of the log joint")
                step = -torch.cholesky_solve(grad, L)
                if prune is not None:
                    # the step's first-order gain, trusted only while the damping is moderate
                    reach = f[idx] + _PRUNE_SAFETY * (grad * step).sum((-1, -2))
                    finite = torch.where(torch.isfinite(f), f, torch.full_like(f, math.inf))
                    best = finite.reshape(-1, K).min(-1).values.repeat_interleave(K)[idx]
                    keep = (reach <= best + prune) | (lam[idx] > _PRUNE_MAX_DAMPING)
                    active[idx[~keep]] = False
                    idx, step = idx[keep], step[keep]
                    if idx.numel() == 0:
                        break
                step = step.reshape(-1, 1, T, dx)
            trial = x.clone()
            trial[idx] = x[idx] + step
            f_t, g_t = by_code(idx, value_grad(trial))
            ok = torch.isfinite(f_t) & (f_t < f[idx])
            gain = torch.where(ok, f[idx] - f_t, torch.zeros_like(f_t))
            x[idx] = torch.where(ok[:, None, None, None], trial[idx], x[idx]).detach()
            f[idx] = torch.where(ok, f_t, f[idx])
            g[idx] = torch.where(ok[:, None, None, None], g_t, g[idx])
            lam[idx] = torch.where(ok, 0.2 * lam[idx], 10.0 * lam[idx])
            done = (ok & (gain < tol)) | (lam[idx] > 1e10)
            active[idx[done]] = False
            history.append(float(f.sum()))
        return x.reshape(*lead, T, dx), history

    def laplace(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        x: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None = None,
        *,
        max_iter: int = 30,
        prune: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        r"""Mean-field Laplace start of q(x): MAP means and ``Sigma_t = (Lambda_tt)^-1``.

        For a narrow q, ``F`` is ``log p(mu, z) - 1/2 sum_t tr(Lambda_tt Sigma_t) + 1/2 sum_t
        log|2 pi e Sigma_t|`` to second order (``Lambda`` the Gauss-Newton precision of the log
        joint), which the mean-field family maximises at ``mu`` = MAP and ``Sigma_t =
        Lambda_tt^-1`` (the inverse *diagonal block*, not the marginal covariance). L-BFGS on the
        exact ``F`` then only polishes this start.

        Args:
            z: ``[..., T, Dz]`` window (NaN rows missing); observed: ``[..., T]`` its mask.
            x: ``[..., K, T, Dx]`` initial states; values: ``[..., K]`` candidate codes.
            g_loc: ``[..., Dg]`` a continuous g, held fixed here.
            max_iter: Levenberg-Marquardt iterations.
            prune: stop refining a candidate once its log joint trails its window's best by
                more than this many nats (``None``: refine all to convergence).

        Returns:
            ``mean [..., K, T, Dx]`` and ``cov [..., K, T, Dx, Dx]``.
        """
        x, _ = self._map_states(z, observed, x, values, g_loc, max_iter=max_iter, prune=prune)
        with torch.no_grad():
            diag, _ = self._precision_blocks(observed, x, values, g_loc)
            cov = torch.cholesky_inverse(psd_cholesky(diag, name="precision block of q(x_t)"))
        return x, symmetrize(cov)

    def _polish(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        values: torch.Tensor,
        loc: torch.Tensor,
        cov: torch.Tensor,
        g_loc: torch.Tensor | None,
        g_cov: torch.Tensor | None,
        steps: int,
        progress: bool,
    ) -> tuple[torch.Tensor | None | list[float], ...]:
        """L-BFGS on the exact F from q = (loc, cov[, q(g)]); returns the new q and the history."""
        f = self._transition_gp(values)
        with torch.no_grad():
            free = self._whiten(f, loc, cov, g_loc, g_cov)
        shapes = [p.shape for p in free]
        nb = loc.shape[:-2].numel()  # independent blocks: windows x candidates

        def unflatten(flat: torch.Tensor) -> list[torch.Tensor]:
            parts = torch.split(flat, [sh.numel() // nb for sh in shapes], dim=-1)
            return [p.reshape(sh) for p, sh in zip(parts, shapes, strict=True)]

        def objective(flat: torch.Tensor) -> torch.Tensor:
            loc, tril, g_l, g_t = self._unwhiten(f, unflatten(flat))
            return -self._free_energy(z, observed, loc, tril, values, g_l, g_t).reshape(nb)

        x0 = torch.cat([p.reshape(nb, -1) for p in free], -1)
        x, history = batched_lbfgs(objective, x0, max_iter=steps, progress=progress)
        with torch.no_grad():
            loc, tril, g_l, g_t = self._unwhiten(f, unflatten(x.detach()))
            g_c = None if g_l is None else g_t @ g_t.transpose(-1, -2)
            return loc, tril @ tril.transpose(-1, -2), g_l, g_c, history

    def infer(
        self,
        z: object,
        *,
        values: object = None,
        steps: int = 0,
        newton_steps: int = 30,
        prune: float | None = 50.0,
        init: str = "nearest",
        progress: bool = False,
    ) -> VBResult:
        """Algorithm 2.2: maximise F(q, g) for every candidate g in one batched optimisation.

        Every window and candidate g is its own problem, all solved in the same tensor calls:

        1. initial states (:meth:`initial_guess`);
        2. :meth:`laplace`: Levenberg-Marquardt to the MAP states, then the mean-field Laplace
           covariances (the optimum of F to second order; cheap: GP predictions at points only);
        3. L-BFGS on the exact closed-form F (:func:`batched_lbfgs`, whitened parameters).

        Without step 2 (``newton_steps=0``) L-BFGS alone stalls hundreds of nats below the
        optimum from a GP-RTSS start: F is stiff (process noise ``alpha_4 = 1e-4``), so a
        first-order method crawls, and the comparison across g is then between unconverged
        bounds.

        Args:
            z: ``[..., T, Dz]`` window (``T >= 2``); NaN rows are missing observations (to be
                forecast or recovered), at least one row must be observed.
            values: candidate codes of a discrete g, ``[K]`` or ``[..., K]`` (default all); e.g.
                the true code ``[..., 1]`` for the oracle H-GPDM.
            steps: maximum L-BFGS iterations on F after the Laplace start.
            newton_steps: maximum Levenberg-Marquardt iterations of the Laplace start (0: start
                L-BFGS from ``init`` directly).
            prune: the Laplace start stops refining a candidate g whose log joint trails the
                window's best candidate by more than ``prune`` nats: its posterior weight is
                below ``exp(-prune)`` either way, and its ``log_evidence`` is then a looser (still
                valid) lower bound. ``None`` refines every candidate to convergence.
            init: initial states (see :meth:`initial_guess`).
            progress: show a progress bar over L-BFGS iterations.

        Returns:
            :class:`VBResult`.
        """
        z, observed = window_mask(z, self.obs_dim)
        z = z.to(self.x1_mean.dtype)
        for name, v in (("steps", steps), ("newton_steps", newton_steps)):
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{name} must be a non-negative int, got {v!r}")
        if prune is not None and not (isinstance(prune, int | float) and prune > 0):
            raise ValueError(f"prune must be a positive number of nats or None, got {prune!r}")
        values = self._candidates(values)
        loc, cov, g_loc, g_cov = self.initial_guess(z, values, init)
        if newton_steps:
            loc, cov = self.laplace(
                z, observed, loc, values, g_loc, max_iter=newton_steps, prune=prune
            )
        history: list[float] = []
        if steps:
            loc, cov, g_loc, g_cov, history = self._polish(
                z, observed, values, loc, cov, g_loc, g_cov, steps, progress
            )
        with torch.no_grad():
            guide = MeanFieldGuide(loc, cov, g_loc, g_cov)
            g_tril = guide.g_scale_tril if guide.has_g else None
            F = self._free_energy(z, observed, guide.loc, guide.scale_tril, values, g_loc, g_tril)
            history = history or [float(-F.sum())]
            if not bool(torch.isfinite(F).all()):
                raise FloatingPointError("the free energy is not finite after optimisation")
            log_prior = self.log_g_prior[values] if self.kind == "discrete" else self.log_g_prior
            posterior = torch.softmax(F + log_prior, dim=-1)
            return VBResult(
                values=values,
                log_evidence=F,
                posterior=posterior,
                g_ml=F.argmax(-1),
                mean=guide.loc.detach(),
                cov=guide.cov.detach(),
                g_mean=guide.g_loc.detach() if guide.has_g else None,
                g_cov=guide.g_cov.detach() if guide.has_g else None,
                guide=guide,
                history=history,
            )

    # ------------------------------------------------------------------ prediction (Sec. 2.3.2)
    def observation_marginals(
        self, mean: torch.Tensor, cov: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Moment-matched ``q(z_t) = int p(z_t | x_t) q(x_t) dx_t`` per time step (FIC).

        Shapes: ``mean [..., T, Dx]``, ``cov [..., T, Dx, Dx]`` -> ``[..., T, Dz]``,
        ``[..., T, Dz, Dz]`` (observation noise included).
        """
        m, S, _ = self.measurement.predict_gaussian(mean, cov, include_noise=True)
        return m, S

    def observation_joint(
        self, mean: torch.Tensor, cov: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        r"""Gaussian ``q(z_{1:T})`` with cross-time covariances (Sec. 2.3.2, App. 2.B).

        Diagonal blocks are the moment-matched ``Cov[z_t]``; for ``s != t`` (independent
        ``x_s, x_t`` under q, so the means do not covary)::

            Cov[z_s,d, z_t,e] = delta_de scale_d^2 (E[k(x_s, x_t)] - l_s^T K^-1 l_t),

        with ``l_t = E[k(X, x_t)]`` and ``E[k(x_s, x_t)]`` the expectation of ``k(x, mu_t)`` at
        ``x ~ N(mu_s, Sigma_s + Sigma_t)`` (exact for stationary and linear kernels alike).

        Shapes: ``mean [..., T, Dx]``, ``cov [..., T, Dx, Dx]`` -> ``mean [..., T, Dz]`` and
        ``cov [..., T * Dz, T * Dz]`` (time-major).
        """
        m, S = self.observation_marginals(mean, cov)
        T, dz = m.shape[-2:]
        gp = self._h
        lt = gp.expected_kernel(mean, cov, gp.X)  # [..., T, N]
        ls_kinv_lt = (lt @ gp.kinv) @ lt.transpose(-1, -2)  # [..., T, T]
        pair = cov[..., :, None, :, :] + cov[..., None, :, :, :]
        c = gp.expected_kernel(mean[..., :, None, :], pair, mean[..., None, :, None, :])[..., 0]
        cross = c - ls_kinv_lt  # [..., T, T]
        scale2 = self.measurement.scale.pow(2)
        full = cross[..., :, None, :, None] * torch.diag(scale2)[:, None, :]
        eye_t = torch.eye(T, dtype=m.dtype, device=m.device)
        full = full * (1.0 - eye_t)[:, None, :, None]
        full = full + S[..., :, :, None, :].mul(eye_t[:, None, :, None])
        return m, symmetrize(full.reshape(*full.shape[:-4], T * dz, T * dz))

    def predict_observations(
        self, z: object, result: VBResult, *, joint: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predict every row of a window from q(x) of the ML value of g (Sec. 2.3.2).

        Missing (NaN) rows are forecast or recovered: with ``joint=True`` from
        ``q(z_missing | z_observed)`` (the joint of :meth:`observation_joint` conditioned on the
        observed rows); with ``joint=False`` from the per-step marginals ``q(z_t)`` (FIC).

        Args:
            z: ``[..., T, Dz]`` the window passed to :meth:`infer`.
            result: its :class:`VBResult`.

        Returns:
            ``mean [..., T, Dz]`` (observed rows unchanged when ``joint``) and ``var [..., T, Dz]``.
        """
        z, observed = window_mask(z, self.obs_dim)
        mean, cov = result.ml_state()
        with torch.no_grad():
            if not joint:
                m, S = self.observation_marginals(mean, cov)
                return m, S.diagonal(dim1=-2, dim2=-1)
            m, S = self.observation_joint(mean, cov)
            T, dz = z.shape[-2:]
            obs = (
                observed[..., :, None].expand(*observed.shape, dz).reshape(*observed.shape[:-1], -1)
            )
            cm, cS = condition_gaussian(
                m.reshape(*m.shape[:-2], T * dz),
                S,
                obs,
                torch.nan_to_num(z).reshape(*z.shape[:-2], T * dz),
            )
            return cm.reshape(*cm.shape[:-1], T, dz), cS.diagonal(dim1=-2, dim2=-1).reshape(
                *cm.shape[:-1], T, dz
            )

    def reconstruct(self, result: VBResult) -> tuple[torch.Tensor, torch.Tensor]:
        """Unconditioned predictions of every row from q(x) of the ML g: the moment-matched
        ``q(z_t)`` means ``[..., T, Dz]`` and variances ``[..., T, Dz]`` (noise included)."""
        mean, cov = result.ml_state()
        with torch.no_grad():
            m, S = self.observation_marginals(mean, cov)
        return m, S.diagonal(dim1=-2, dim2=-1)

    def forecast(
        self, z: object, *, residual: str | None = None, **infer_kwargs: object
    ) -> tuple[torch.Tensor, torch.Tensor, Any]:
        """Forecast ``z_{T+1}`` from a window ``z_{1:T}`` (Sec. 2.3.2, Tables 2.1-2.4 protocol).

        Runs :meth:`infer` on ``z_{1:T}`` with a missing row appended, picks the ML value of g
        and conditions the joint ``q(z_{1:T+1})`` on the observed rows.

        Args:
            z: ``[..., T, Dz]`` windows (NaN marks missing values).
            residual: ``None`` (the thesis's forecast) or ``"ar1"``: the window's deviation from
                the model's reconstruction continues as an AR(1) process whose coefficient is
                estimated from the window (:func:`~hgpdm_torch.inference.residual.
                ar1_residual_forecast`); for new recordings that sit off the training manifold.
            **infer_kwargs: passed to :meth:`infer`.

        Returns:
            ``mean [..., Dz]``, ``var [..., Dz]`` of the next observation, and the result.
        """
        if residual is not None:
            check_choice(residual, "residual", ("ar1",))
        z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
        nan = torch.full((*z.shape[:-2], 1, z.shape[-1]), float("nan"), dtype=z.dtype)
        window = torch.cat([z, nan], -2)
        res = self.infer(window, **infer_kwargs)
        if residual is None:
            m, v = self.predict_observations(window, res)
            return m[..., -1, :], v[..., -1, :], res
        rec, var = self.reconstruct(res)
        mean, var, _ = ar1_residual_forecast(z, rec[..., :-1, :], rec[..., -1, :], var[..., -1, :])
        return mean, var, res


def batched_lbfgs(
    fun: Callable[[torch.Tensor], torch.Tensor],
    x0: torch.Tensor,
    *,
    max_iter: int = 50,
    history_size: int = 10,
    tol_grad: float = 1e-6,
    tol_change: float = 1e-9,
    max_step: float = 3.0,
    progress: bool = False,
) -> tuple[torch.Tensor, list[float]]:
    """Minimise ``B`` independent problems at once by L-BFGS with per-problem state.

    One call of ``fun`` evaluates all problems (one batched free energy), but each problem keeps
    its own curvature pairs, step length (Armijo backtracking) and stopping test, so an
    ill-conditioned window does not slow the others, as it would in one L-BFGS over the sum.

    Args:
        fun: ``x [B, P] -> [B]`` objective values (differentiable).
        x0: ``[B, P]`` starting points.
        max_iter: maximum iterations.
        history_size: curvature pairs kept per problem.
        tol_grad: a problem stops when its largest gradient entry is below this.
        tol_change: ... or when its objective changes by less than this (relative) in a step.
        max_step: largest change of any variable in one step.
        progress: show a tqdm bar over iterations.

    Returns:
        The minimisers ``[B, P]`` and ``sum fun`` after each iteration.
    """
    if x0.dim() != 2:
        raise ValueError(f"x0 must have shape [B, P], got {tuple(x0.shape)}")
    B, P, m = x0.shape[0], x0.shape[1], history_size

    def value_grad(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = x.detach().requires_grad_(True)
        try:
            with torch.enable_grad():
                v = fun(x)
                (grad,) = torch.autograd.grad(v.sum(), x)
        except (torch.linalg.LinAlgError, CholeskyError, ValueError):
            # a trial point outside the domain (e.g. a covariance overflow): reject the step
            return torch.full_like(x[:, 0], math.inf), torch.zeros_like(x)
        return v.detach(), grad

    x = x0.detach().clone()
    f, g = value_grad(x)
    S = x.new_zeros(B, m, P)
    Y = x.new_zeros(B, m, P)
    rho = x.new_zeros(B, m)  # 0 marks an empty slot
    active = g.abs().amax(-1) > tol_grad
    history = [float(f.sum())]
    for _ in trange(max_iter, disable=not progress, desc="VB (Alg. 2.2)", leave=False):
        if not bool(active.any()):
            break
        # two-loop recursion, newest pair last; empty slots have rho = 0 and drop out
        q = -g
        alphas = []
        for j in range(m - 1, -1, -1):
            a = rho[:, j] * (S[:, j] * q).sum(-1)
            q = q - a[:, None] * Y[:, j]
            alphas.append(a)
        sy, yy = (S[:, -1] * Y[:, -1]).sum(-1), Y[:, -1].pow(2).sum(-1)
        first = 1.0 / g.abs().sum(-1).clamp_min(1.0)  # no pairs yet: a short gradient step
        gamma = torch.where(rho[:, -1] > 0, sy / yy.clamp_min(1e-300), first)
        r = gamma[:, None] * q
        for j, a in zip(range(m), reversed(alphas), strict=True):
            b = rho[:, j] * (Y[:, j] * r).sum(-1)
            r = r + (a - b)[:, None] * S[:, j]
        slope = (g * r).sum(-1)
        bad = slope >= 0  # not a descent direction: fall back to the gradient
        r = torch.where(bad[:, None], -first[:, None] * g, r)
        slope = (g * r).sum(-1)
        # per-problem Armijo backtracking; finished problems take a zero step
        # steps move no free variable by more than max_step (keeps trial covariances finite)
        step = active.to(x.dtype) * (max_step / r.abs().amax(-1).clamp_min(1e-300)).clamp_max(1.0)
        accepted = ~active
        f_new, g_new = f, g
        for _ in range(30):
            trial = x + step[:, None] * r
            f_t, g_t = value_grad(trial)
            ok = (f_t <= f + 1e-4 * step * slope) & torch.isfinite(f_t)
            take = ok & ~accepted
            f_new = torch.where(take, f_t, f_new)
            g_new = torch.where(take[:, None], g_t, g_new)
            accepted = accepted | ok
            if bool(accepted.all()):
                break
            step = torch.where(accepted, step, 0.5 * step)
        step = torch.where(accepted, step, torch.zeros_like(step))
        s_k = step[:, None] * r
        y_k = g_new - g
        sy_k = (s_k * y_k).sum(-1)
        good = active & accepted & (sy_k > 1e-10 * y_k.pow(2).sum(-1).sqrt() * s_k.norm(dim=-1))
        S = torch.where(good[:, None, None], torch.cat([S[:, 1:], s_k[:, None]], 1), S)
        Y = torch.where(good[:, None, None], torch.cat([Y[:, 1:], y_k[:, None]], 1), Y)
        new_rho = torch.cat([rho[:, 1:], (1.0 / sy_k.clamp_min(1e-300))[:, None]], 1)
        rho = torch.where(good[:, None], new_rho, rho)
        x = x + s_k
        change = (f - f_new).abs() <= tol_change * f.abs().clamp_min(1.0)
        f, g = f_new, g_new
        active = active & accepted & ~change & (g.abs().amax(-1) > tol_grad)
        history.append(float(f.sum()))
    return x, history
