r"""The GP-ADF measurement update of the online filter (Eq. 25, 32-35).

:class:`LinearMeasurement` precomputes the exact update for a linear measurement kernel (Eq. 20,
the IDDM's usual choice); any other kernel uses
:func:`~hgpdm_torch.inference.filtering.gp_adf_update` on the measurement GP.

Shapes: ``Dx`` latent, ``Dz`` observed; ``...`` any leading dims (streams B, intentions K).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

from ...expectations import kernel_leaves, split_terms
from ...gaussian import log_density_terms
from ...gp import GPPosterior
from ...linalg import cholesky_logdet, psd_cholesky, symmetrize
from ...moments import input_operations
from ...tiling import OpCount
from ..filtering import gp_adf_update

__all__ = ["LinearMeasurement", "linear_measurement", "measurement_operations"]


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

    @functools.cached_property
    def native_terms(self) -> torch.Tensor:
        """``[Dz k + k Dx + Dx^2 + 2 Dz + 2]``: U, R, Q, the offset, the scale, the noise and
        ``2 sum log s``, flat (:func:`hgpdm_torch.native.predictive_step`'s ``meas``)."""
        dz = self.U.shape[0]
        parts = (self.U, self.R, self.Q, self.offset.expand(dz), self.scale, self.noise,
                 self.log_scale2)  # fmt: skip
        return torch.cat([t.reshape(-1) for t in parts]).contiguous()

    def operations(self) -> OpCount:
        """Work of :meth:`update` per Gaussian (the floor's count), ``k = min(Dx, Dz)``:
        ``2 Dx^2`` for ``v``, ``2 Dz k`` for the projections of ``z``, ``k Dx`` for ``r``,
        ``k Dx^2 + k^2 Dx`` for ``S``, ``k^3 / 3`` for its Cholesky factor, ``k^2 (Dx + 1)``
        for the solves, ``Dx k + Dx^2 k`` for the posterior and ``k + Dz`` for the density;
        ``Dz`` divisions and 2 logarithms counted as exponentials."""
        dz, k = self.U.shape
        dx = self.R.shape[1]
        madds = 2 * dx * dx + 2 * dz * k + k * dx + k * dx * dx + k * k * dx + k**3 / 3
        madds += k * k * (dx + 1) + dx * k + dx * dx * k + k + dz
        return OpCount(exps=2 + dz, madds=madds)

    def moments(
        self, mu: torch.Tensor, P: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The predictive moments of ``z`` at ``x ~ N(mu, P)`` (the class docstring's mean, cov
        and ``Cov[x, z]``: :meth:`GPPosterior.predict_gaussian
        <hgpdm_torch.gp.GPPosterior.predict_gaussian>` with ``include_noise=True``) in
        ``O(Dx Dz^2)``. Shapes ``[..., Dx]``, ``[..., Dx, Dx]`` -> ``[..., Dz]``,
        ``[..., Dz, Dz]``, ``[..., Dx, Dz]``."""
        W = (self.U @ self.R).transpose(-1, -2) * self.scale  # [Dx, Dz]
        second = P + mu[..., :, None] * mu[..., None, :]
        v = (self.Q * second).sum((-1, -2)) + self.noise  # [...]
        cross = P @ W
        cov = symmetrize(W.transpose(-1, -2) @ cross) + torch.diag_embed(
            v[..., None] * self.scale.pow(2)
        )
        return mu @ W + self.offset, cov, cross

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


def measurement_update(posterior: GPPosterior, dtype: torch.dtype):
    """The fastest exact GP-ADF measurement update for this GP: ``(mu, P, z) -> (m, P, ll)``."""
    try:
        return LinearMeasurement(posterior, dtype).update
    except TypeError:
        post = posterior.to_dtype(dtype)
        return functools.partial(gp_adf_update, post)  # picklable, unlike a lambda


def linear_measurement(update: Callable[..., object]) -> LinearMeasurement | None:
    """The :class:`LinearMeasurement` behind a :func:`measurement_update` result, or ``None``
    (the generic GP-ADF update)."""
    owner = getattr(update, "__self__", None)
    return owner if isinstance(owner, LinearMeasurement) else None


def measurement_operations(update: Callable[..., object], dx: int, inputs: int = 1) -> OpCount:
    """Work of one measurement update (:func:`measurement_update`'s result) per Gaussian of
    ``Dx`` dims: :meth:`LinearMeasurement.operations`, or for
    :func:`~hgpdm_torch.inference.filtering.gp_adf_update` the moment matching of the
    measurement GP (:func:`~hgpdm_torch.moments.input_operations`) and the conditioning on
    ``z`` (``Dz^3 / 3`` for the Cholesky factor, ``Dz^2 (Dx + 1)`` for the solves, ``Dx^2 Dz``
    for the posterior covariance), ``inputs`` Gaussians sharing a call."""
    linear = linear_measurement(update)
    if linear is not None:
        return linear.operations()
    post = update.args[0]
    leaves = kernel_leaves(post.kernel, post.input_dim)
    terms = split_terms(leaves, post.train_inputs, None, post.input_dim)
    dz = post.output_dim
    ops = input_operations(terms, post.train_inputs.shape[0], dz, inputs=inputs)
    return ops + OpCount(exps=1, madds=dz**3 / 3 + dz * dz * (dx + 1) + dx * dx * dz)
