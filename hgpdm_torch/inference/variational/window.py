r"""A fitted model as seen by a window of new observations: the objectives that VB and MAP
inference maximise over the window's latent states (thesis Eq. 8-9, 13, 15-17).

:class:`WindowModel` holds what every window shares: the measurement GP ``h`` and the transition
GP ``f`` conditioned on the MAP training latents, the prior ``p(x_1) = N(m_1, S_1)`` of a window's
first state, the prior over g and the candidate values of a discrete g. On it live

- the FIC log joint (Eq. 8-9), the MAP objective and Laplace's expansion point::

      log p(x_{1:T}, z_obs | g) = log N(x_1 | m_1, S_1)
          + sum_t log N(x_{t+1} | m_x(x_t, g), sigma_x^2(x_t, g) diag(v^-2))
          + sum_{t obs} log N(z_t | m_z(x_t), sigma_z^2(x_t) diag(scale^2)),

  with its Fisher precision (the expected Hessian, block-tridiagonal in time), where ``v`` are
  the transition GP's output scales (ones but for ``scale_transitions=True``: the thesis's
  ``I``);
- the negative free energy of Eq. 13 under the mean-field q of Eq. 11, in closed form::

      F(q, g) = sum_t E_q[log p(z_t | x_t)] + sum_t E_q[log p(x_{t+1} | x_t, g)]
                - H(q(x_1), p(x_1)) + H(q)     [+ E_q[log p(g)] + H(q(g)) for a continuous g]

  where the GP predictive variances ``sigma_z^2``, ``sigma_x^2`` are evaluated at the variational
  means (Eq. 15-17, the thesis's approximation;
  docs/design/math.md#vb-variances-at-the-variational-means) and the expected squared errors
  come from :mod:`~hgpdm_torch.inference.variational.gaussian_input` (App. 2.A).

A discrete g's transition kernel is block-diagonal, so each value touches only its own training
points (``GPPosterior``'s per-code blocks). Missing observations (Sec. 2.3.2): a row of NaN drops
its measurement term.

Shapes: ``T`` window length, ``K`` candidate values of g, ``Dx`` latent dim, ``Dz`` observation
dim, ``Dg`` dim of a continuous g; ``...`` leading batch dims (e.g. windows).
"""

from __future__ import annotations

import torch

from ...gaussian import (
    entropy,
    expected_log_density,
    independent_joint,
    log_density,
    log_density_terms,
)
from ...linalg import psd_cholesky, symmetrize
from ...models import GPDM, HGPDM
from ...validation import as_tensor
from ..filtering import check_window_model
from .gaussian_input import GaussianInputGP, expected_sq_error

__all__ = ["WindowModel", "window_mask"]


def window_mask(z: object, obs_dim: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a window ``z [..., T, Dz]`` whose NaN rows are missing observations.

    Returns:
        ``z`` on the device and in the dtype of ``like`` (the window model's), and the
        ``[..., T]`` boolean mask of observed rows.

    Raises:
        ValueError: ``T < 2``, wrong ``Dz``, partially missing rows, or a window without any
            observed row.
    """
    z = as_tensor(z, "z", min_ndim=2, allow_nan=True).to(like)
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
    pair: object, name: str, dim: int, like: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Validate a ``(mean [dim], cov [dim, dim])`` pair given by the user (dtype, device of
    ``like``)."""
    if not isinstance(pair, tuple | list) or len(pair) != 2:
        raise TypeError(f"{name} must be a (mean, cov) pair, got {type(pair).__name__}")
    opts = {"dtype": like.dtype, "device": like.device}
    mean = as_tensor(pair[0], f"{name} mean", ndim=1, **opts)
    cov = as_tensor(pair[1], f"{name} cov", ndim=2, **opts)
    if mean.shape != (dim,) or cov.shape != (dim, dim):
        raise ValueError(f"{name} must be (mean [{dim}], cov [{dim}, {dim}])")
    return mean, cov


class WindowModel:
    """The GPs, priors and objectives of a fitted GPDM / H-GPDM for windows of new observations.

    Shared by :class:`~hgpdm_torch.inference.variational.VariationalInference` and
    :class:`~hgpdm_torch.inference.map.MAPInference`.

    Args:
        model: a fitted GPDM / HGPDM / IDDM (see
            :class:`~hgpdm_torch.inference.variational.VariationalInference`).
        x1_prior: ``(mean, cov)`` of ``p(x_1)`` (default: fitted to the training latents).
        g_prior: the prior over g (default: uniform / fitted to the training intentions).
        measurement_points: route the measurement GP through at most this many pseudo-inputs
            (DTC, :meth:`~hgpdm_torch.models.GPDM.measurement_posterior`; default the exact GP).

    Attributes:
        kind: ``"none"`` (GPDM), ``"discrete"`` or ``"continuous"``.
        values: ``[K]`` all codes of a discrete g (empty otherwise).
        measurement, transition: the models' :class:`~hgpdm_torch.gp.GPPosterior` s.
        h: the measurement GP at Gaussian inputs (:class:`GaussianInputGP`).
    """

    def __init__(
        self, model: GPDM, *, x1_prior: tuple[object, object] | None = None,
        g_prior: object = None, measurement_points: int | None = None,
    ) -> None:  # fmt: skip
        check_window_model(model, GPDM, "a GPDM/HGPDM", "window inference carries no phase")
        self.model = model
        self.kind = model.intention if isinstance(model, HGPDM) else "none"
        self.measurement = model.measurement_posterior(measurement_points)
        self.transition = model.transition_posterior()
        if self.transition.noise.dim() != 0 and self.transition.code_noise is None:
            # a noise per training point is fine for the training factor, but a new step then
            # needs the noise of its code (a model with noise_per_value=True gives one)
            raise ValueError(
                "variational inference needs the process noise of a new step: one shared noise "
                "or one per code of a discrete g (code_noise); this transition GP has only a "
                "noise per training point"
            )
        self.latent_dim = model.latent_dim
        self.obs_dim = model.obs_dim
        # [Dx] variance factors 1 / v_d^2 of a model with scale_transitions, else None (the
        # isotropic algebra of Eq. 15-17, unchanged to the bit)
        t_scale2 = self.transition.scale.pow(2)
        self.t_scale2 = None if bool((t_scale2 == 1).all()) else t_scale2
        like = self.measurement.train_inputs
        opts = {"dtype": like.dtype, "device": like.device}
        self.h = GaussianInputGP(self.measurement)
        self._f_cache: dict[tuple, GaussianInputGP] = {}
        lat = model.latent.detach()
        if x1_prior is None:
            m1 = lat.mean(0)
            S1 = torch.cov(lat.T).reshape(self.latent_dim, self.latent_dim)
            S1 = S1 + 1e-6 * torch.eye(self.latent_dim, **opts)
        else:
            m1, S1 = _gaussian_argument(x1_prior, "x1_prior", self.latent_dim, like)
        self.x1_mean, self.x1_cov = m1, symmetrize(S1)
        self.x1_chol = psd_cholesky(self.x1_cov, name="x1_prior covariance")
        self.g_dim = 0
        if self.kind == "discrete":
            K = model.num_values
            self.values = torch.arange(K, device=like.device)
            prior = torch.full((K,), 1.0 / K, **opts) if g_prior is None else g_prior
            prior = as_tensor(prior, "g_prior", ndim=1, **opts)
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
            self.values = torch.zeros(0, dtype=torch.long, device=like.device)
            self.log_g_prior = torch.zeros(1, **opts)
            self._f = GaussianInputGP(self.transition)
        if self.kind == "continuous":
            g = model.intentions
            self.g_dim = g.shape[1]
            if g_prior is None:
                mg = g.mean(0)
                Sg = torch.cov(g.T).reshape(self.g_dim, self.g_dim) if g.shape[0] > 1 else None
                if Sg is None or bool((Sg.diagonal() <= 0).any()):
                    Sg = torch.eye(self.g_dim, **opts)
            else:
                mg, Sg = _gaussian_argument(g_prior, "g_prior", self.g_dim, like)
            self.g_prior_mean, self.g_prior_cov = mg, symmetrize(Sg)
            self.g_chol = psd_cholesky(self.g_prior_cov, name="g_prior covariance")

    # ------------------------------------------------------------------ candidates of g
    def candidates(self, values: object) -> torch.Tensor:
        """Validated candidate codes ``[K]`` or ``[..., K]`` of a discrete g (default all)."""
        if self.kind != "discrete":
            if values is not None:
                raise ValueError(f"values applies to a discrete g only (model has {self.kind!r})")
            return self.values
        if values is None:
            return self.values
        v = torch.as_tensor(values, device=self.values.device)
        if v.is_floating_point():
            if not bool((v == v.round()).all()):
                raise ValueError("values must be integer codes of g")
            v = v.long()
        if v.dim() == 0:
            v = v[None]
        if bool(((v < 0) | (v >= self.model.num_values)).any()):
            raise ValueError(f"values must be codes in [0, {self.model.num_values - 1}]")
        return v

    def log_prior(self, values: torch.Tensor) -> torch.Tensor:
        """``log p(g)`` of the candidates ``[..., K]`` (``[1]`` zeros without a discrete g)."""
        return self.log_g_prior[values] if self.kind == "discrete" else self.log_g_prior

    def transition_gp(self, values: torch.Tensor) -> GaussianInputGP:
        """The transition GP of candidates ``values [..., K]`` at Gaussian inputs."""
        if self.kind != "discrete":
            return self._f
        # [..., K] codes -> blocks [..., K, 1, N, .] (the 1 is the time axis); kept per set of
        # codes, since the optimisers ask for the same candidates (or one code) at every step
        key = (tuple(values.shape), tuple(values.flatten().tolist()), values.device)
        if key not in self._f_cache:
            if len(self._f_cache) > 64:
                self._f_cache.clear()
            self._f_cache[key] = GaussianInputGP(self.transition, values[..., None])
        return self._f_cache[key]

    @staticmethod
    def transition_inputs(x: torch.Tensor, g_loc: torch.Tensor | None) -> torch.Tensor:
        """Transition inputs ``[x_t, g]`` for states ``x [..., K, S, Dx]`` (g: q(g)'s mean)."""
        if g_loc is None:
            return x
        return torch.cat([x, g_loc[..., None, None, :].expand(*x.shape[:-1], -1)], -1)

    # ------------------------------------------------------------------ the free energy
    def free_energy(
        self,
        z: torch.Tensor,
        observed: torch.Tensor,
        loc: torch.Tensor,
        scale_tril: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None,
        g_scale_tril: torch.Tensor | None,
    ) -> torch.Tensor:
        r"""Negative free energy ``F(q, g)`` ``[..., K]`` of Eq. 13 with Eq. 15-17.

        Args:
            z: ``[..., T, Dz]`` window and observed: ``[..., T]`` its mask (:func:`window_mask`).
            loc: ``[..., K, T, Dx]`` means of q(x); scale_tril: ``[..., K, T, Dx, Dx]``.
            values: ``[..., K]`` candidate codes (:meth:`candidates`).
            g_loc: ``[..., Dg]`` mean of q(g) of a continuous g (else ``None``).
            g_scale_tril: ``[..., Dg, Dg]`` its Cholesky factor.
        """
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
        var = self.h.var_at_mean(loc)[..., None] * h.scale.pow(2)  # [..., K, T, Dz]
        m, m2 = self.h.mean_moments(loc, cov)
        ll_z = log_density_terms(expected_sq_error(zc, None, m, m2) / var, torch.log(var), 1)
        ll_z = (ll_z.sum(-1) * observed[..., None, :].to(ll_z.dtype)).sum(-1)
        # Eq. 17: transitions x_t -> x_{t+1} (with q(g) appended to the input if continuous)
        mu_in, cov_in = loc[..., :-1, :], cov[..., :-1, :, :]
        if g_loc is not None:
            g_cov = g_scale_tril @ g_scale_tril.transpose(-1, -2)
            mu_in, cov_in = independent_joint(
                mu_in, cov_in, g_loc[..., None, None, :], g_cov[..., None, None, :, :]
            )
        f = self.transition_gp(values)
        s2 = f.var_at_mean(mu_in)  # [..., K, T-1]
        m, m2 = f.mean_moments(mu_in, cov_in)
        nxt_var = cov[..., 1:, :, :].diagonal(dim1=-2, dim2=-1)
        err = expected_sq_error(loc[..., 1:, :], nxt_var, m, m2)
        ll_x = self._transition_terms(err, s2)
        # the first state's expected log prior (minus a cross-entropy) and the entropy of q
        x1 = loc[..., 0, :], scale_tril[..., 0, :, :]
        l1 = expected_log_density(*x1, self.x1_mean, self.x1_chol)
        F = ll_z + ll_x + l1 + entropy(scale_tril).sum(-1)
        if g_loc is not None:
            lg = expected_log_density(g_loc, g_scale_tril, self.g_prior_mean, self.g_chol)
            F = F + (entropy(g_scale_tril) + lg)[..., None]
        return F

    # ------------------------------------------------------------------ the log joint (MAP)
    def log_joint(
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
        m, v = self.h.predict_point(x)
        var = v[..., None] * h.scale.pow(2)
        r = (torch.nan_to_num(z) - h.offset)[..., None, :, :] - m
        lz = log_density_terms(r.pow(2) / var, torch.log(var), 1).sum(-1)
        lz = (lz * observed[..., None, :].to(lz.dtype)).sum(-1)
        inp = self.transition_inputs(x[..., :-1, :], g_loc)
        mx, vx = self.transition_gp(values).predict_point(inp)
        lx = self._transition_terms((x[..., 1:, :] - mx).pow(2), vx)
        return lz + lx + log_density(x[..., 0, :], self.x1_mean, self.x1_chol)

    def _transition_terms(self, err: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
        """``sum_t log N`` of the transitions from their (expected) squared errors ``err [...,
        T-1, Dx]`` and the GP variance ``var [..., T-1]``, isotropic (Eq. 17) or scaled per latent
        dim (``var / v_d^2``, ``scale_transitions``) -> ``[...]``."""
        if self.t_scale2 is None:
            dx = self.latent_dim
            return log_density_terms(err.sum(-1) / var, dx * torch.log(var), dx).sum(-1)
        var = var[..., None] * self.t_scale2
        return log_density_terms(err / var, torch.log(var), 1).sum((-1, -2))

    def precision_blocks(
        self,
        observed: torch.Tensor,
        x: torch.Tensor,
        values: torch.Tensor,
        g_loc: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Fisher precision (the expected Hessian) of the log joint at states ``x [..., K, T, Dx]``.

        Each Gaussian term ``N(y | m(x), sigma^2(x) diag(s^2))`` of ``D`` outputs contributes its
        Fisher information ``J^T diag(1 / (sigma^2 s^2)) J + D/2 grad log sigma^2 (grad log
        sigma^2)^T``: the Gauss-Newton ``J^T J`` of the residuals whitened by the GP predictive
        std (the Jacobians from the GP mean's, :meth:`GaussianInputGP.predict_point`) plus the
        curvature of the variance, which Gauss-Newton omits. Without it Levenberg-Marquardt
        crawls wherever the predictive variance changes fast (a narrow kernel, the edge of the
        training latents: on Weird Walking's windows 30 iterations left the median window 6 nats
        and one in ten more than 180 nats short of the maximum, ``python -m benchmarks
        map_solver``). The precision is
        block-tridiagonal in time (the variance terms touch only the diagonal blocks).

        Returns:
            diagonal blocks ``[..., K, T, Dx, Dx]`` and blocks ``(t, t+1)`` ``[..., K, T-1, Dx,
            Dx]``.
        """
        dx, dz = self.latent_dim, self.obs_dim
        _, vh, Jh, dvh = self.h.predict_point(x, jacobian=True)  # Jh [..., K, T, Dz, Dx]
        obs = observed[..., None, :, None].to(x.dtype)
        w = obs / (vh[..., None] * self.measurement.scale**2)
        diag = Jh.transpose(-1, -2) @ (w[..., None] * Jh)
        glh = obs * dvh / vh[..., None]  # grad log sigma_z^2, zero on missing rows
        diag = diag + 0.5 * dz * glh[..., :, None] * glh[..., None, :]
        inp = self.transition_inputs(x[..., :-1, :], g_loc)
        _, vf, Jf, dvf = self.transition_gp(values).predict_point(inp, jacobian=True)
        Jf = Jf[..., :dx]  # d m_x / d x_t  [..., K, T-1, Dx, Dx]
        glf = dvf[..., :dx] / vf[..., None]  # grad log sigma_x^2 (x_t only, not g)
        eye = torch.eye(dx, dtype=x.dtype, device=x.device)
        pad = torch.zeros_like(diag[..., :1, :, :])
        var_curv = 0.5 * dx * glf[..., :, None] * glf[..., None, :]
        diag = diag + torch.cat([var_curv, pad], -3)
        if self.t_scale2 is None:
            inv = (1.0 / vf)[..., None, None]
            diag = diag + torch.cat([Jf.transpose(-1, -2) @ Jf * inv, pad], -3)
            diag = diag + torch.cat([pad, eye * inv], -3)
            off = -Jf.transpose(-1, -2) * inv
        else:  # per-dim precisions P = diag(v_d^2 / vf): J^T P J, P and -J^T P
            inv = (1.0 / vf)[..., None] / self.t_scale2  # [..., K, T-1, Dx]
            PJ = inv[..., None] * Jf
            diag = diag + torch.cat([Jf.transpose(-1, -2) @ PJ, pad], -3)
            diag = diag + torch.cat([pad, torch.diag_embed(inv)], -3)
            off = -PJ.transpose(-1, -2)
        prior = torch.cholesky_inverse(self.x1_chol)
        diag = diag + torch.cat([prior.expand_as(pad), torch.zeros_like(diag[..., 1:, :, :])], -3)
        return diag, off

    @staticmethod
    def dense(diag: torch.Tensor, off: torch.Tensor) -> torch.Tensor:
        """Dense ``[..., T Dx, T Dx]`` matrix from tridiagonal blocks (time-major)."""
        T, dx = diag.shape[-3], diag.shape[-1]
        full = diag.new_zeros(*diag.shape[:-3], T, T, dx, dx)
        i = torch.arange(T, device=diag.device)
        full[..., i, i, :, :] = diag
        full[..., i[:-1], i[1:], :, :] = off
        full[..., i[1:], i[:-1], :, :] = off.transpose(-1, -2)
        return full.transpose(-3, -2).reshape(*diag.shape[:-3], T * dx, T * dx)
