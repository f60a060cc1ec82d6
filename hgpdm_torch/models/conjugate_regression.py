"""Conjugate Bayesian linear regression with matrix-normal inverse-Wishart parameters: the algebra
of :class:`~hgpdm_torch.models.LinearIDDM`, one phase at a time.

Model of one phase, ``n`` transitions with inputs ``U [n, P]`` and targets ``Y [n, Dz]``::

    Y = U W + E,   rows of E ~ N(0, Sigma),   W | Sigma ~ MN(0, I / lambda, Sigma),
    Sigma ~ IW(psi I, Dz + 2)

``noise="diagonal"`` replaces ``Sigma`` by independent per-dimension variances (inverse-gamma,
the ``Dz = 1`` case of the prior per dimension), ``noise="isotropic"`` by ``sigma^2 I`` with
``sigma^2 ~ IG(2, psi)`` (the GPDM's assumption). Posterior (:func:`posterior`):
``Lambda_n = U^T U + lambda I``, ``M_n = Lambda_n^-1 U^T Y``,
``Psi_n = psi I + Y^T Y - M_n^T Lambda_n M_n`` (computed as ``psi I + R^T R + lambda M_n^T M_n``
with the residuals ``R = Y - U M_n``, which does not cancel in float32), ``nu_n = Dz + 2 + n``.
The predictive of the next target given ``u`` (:func:`student_t_predictive`) is Student-t with
``nu_n - Dz + 1`` degrees of freedom, location ``M_n^T u`` and scale matrix
``(1 + u^T Lambda_n^-1 u) Psi_n / (nu_n - Dz + 1)``; the evidence ``p(Y | U)`` is
:func:`log_marginal`.

The inputs (:func:`regression_inputs`) are ``u = [z, phi(g), 1, phi(g) (x) V^T z]``: the state,
the intention features (:func:`intention_features`), a constant and, optionally, the intention
times the state's projection on the partial-least-squares directions ``V`` of the states on the
intention (:func:`pls_directions`).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from pyro.distributions import MultivariateStudentT
from torch.distributions import StudentT

from ..linalg import cholesky_logdet

__all__ = [
    "default_grid",
    "intention_features",
    "log_marginal",
    "pls_directions",
    "posterior",
    "regression_inputs",
    "student_t_log_prob",
    "student_t_predictive",
    "student_t_sample",
    "total_log_marginal",
]


def intention_features(g: torch.Tensor, intention: str, num_values: int | None) -> torch.Tensor:
    """``phi(g)``: g itself, or the one-hot code of a discrete g."""
    if intention == "continuous":
        return g
    return torch.nn.functional.one_hot(g[:, 0].long(), num_values).to(g.dtype)


def default_grid(g: torch.Tensor, intention: str, num_values: int | None, num: int) -> torch.Tensor:
    """``[K, 1]``: every code of a discrete g, or ``num`` values over the range of a continuous
    ``g [J, 1]``."""
    if intention == "discrete":
        return torch.arange(num_values, dtype=g.dtype, device=g.device)[:, None]
    return torch.linspace(float(g.min()), float(g.max()), num, dtype=g.dtype,
                          device=g.device)[:, None]  # fmt: skip


def pls_directions(z: torch.Tensor, phi: torch.Tensor, rank: int) -> torch.Tensor:
    """``[Dz, rank]``: the partial-least-squares directions of the states ``z [n, Dz]`` on the
    intention features ``phi [n, P]`` (sklearn, unscaled: ``z`` is standardised already).
    Zeros, with a warning, where they cannot be estimated: fewer than ``rank + 1`` transitions,
    or an intention that does not vary over them (no interaction in that phase)."""
    zeros = z.new_zeros(z.shape[1], rank)
    if rank == 0:
        return zeros
    if len(z) < rank + 1 or bool((phi.std(0) == 0).all()):
        warnings.warn(
            f"LinearIDDM: a phase has {len(z)} training transitions"
            + (" whose intentions are all equal" if len(z) >= rank + 1 else "")
            + f"; its interaction directions (rank {rank}) cannot be estimated and are left "
            "out (zeros)",
            stacklevel=4,
        )
        return zeros
    from sklearn.cross_decomposition import PLSRegression

    pls = PLSRegression(rank, scale=False).fit(z.cpu().numpy(), phi.cpu().numpy())
    return torch.as_tensor(pls.x_rotations_, dtype=z.dtype, device=z.device)


def regression_inputs(z: torch.Tensor, phi: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """``u = [z, phi(g), 1, phi(g) (x) (V^T z)]``: ``z [..., Dz]``, ``phi [..., P]``,
    ``V [Dz, r]`` -> ``[..., Dz + P + 1 + P r]`` (the last block empty for ``r = 0``)."""
    inter = phi[..., :, None] * (z @ directions)[..., None, :]
    one = torch.ones(*z.shape[:-1], 1, dtype=z.dtype, device=z.device)
    return torch.cat([z, phi, one, inter.flatten(-2)], -1)


def posterior(
    u: torch.Tensor, y: torch.Tensor, lam: float, psi: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Conjugate update of one phase from ``u [n, P]``, ``y [n, Dz]``: ``Lambda_n [P, P]``,
    ``M_n [P, Dz]``, ``Psi_n [Dz, Dz]`` (prior ``psi I`` included) and ``nu_n``."""
    p, d = u.shape[1], y.shape[1]
    precision = u.T @ u + lam * torch.eye(p, dtype=u.dtype, device=u.device)
    coef = torch.cholesky_solve(u.T @ y, torch.linalg.cholesky(precision))
    # Y^T Y - M^T Lambda_n M as a sum of squares: the subtraction cancels in float32
    resid = y - u @ coef
    scatter = resid.T @ resid + lam * coef.T @ coef
    scatter = 0.5 * (scatter + scatter.T) + psi * torch.eye(d, dtype=u.dtype, device=u.device)
    return precision, coef, scatter, torch.tensor(d + 2.0 + len(u), dtype=u.dtype, device=u.device)


def total_log_marginal(
    stats: list[tuple[torch.Tensor, ...]], kind: str, prior: tuple[float, float]
) -> float:
    """The evidence of all phases: the sum of :func:`log_marginal` over ``stats``."""
    return float(sum(log_marginal(*st, kind, *prior) for st in stats))


def log_marginal(
    precision: torch.Tensor, coef: torch.Tensor, scatter: torch.Tensor, dof: torch.Tensor,
    noise: str, lam: float, psi: float,
) -> torch.Tensor:  # fmt: skip
    """``log p(Y | U)`` of one phase: the matrix-normal inverse-Wishart evidence
    ``pi^(-n D/2) (|Lambda_0| / |Lambda_n|)^(D/2) |Psi_0|^(nu_0/2) / |Psi_n|^(nu_n/2)
    Gamma_D(nu_n/2) / Gamma_D(nu_0/2)``; per dimension with ``D = 1`` for diagonal noise; with
    the inverse-gamma ``IG(2, psi)`` and ``(2 pi)^(-n D/2)`` for isotropic noise."""
    p, d = coef.shape
    n = float(dof) - d - 2
    coef_term = 0.5 * (p * math.log(lam) - cholesky_logdet(torch.linalg.cholesky(precision)))
    if noise == "isotropic":
        a_n = 2.0 + n * d / 2
        b_n = psi + 0.5 * (scatter.trace() - d * psi)
        return (-0.5 * n * d * math.log(2 * math.pi) + d * coef_term + 2.0 * math.log(psi)
                - a_n * b_n.log() + math.lgamma(a_n) - math.lgamma(2.0))  # fmt: skip
    if noise == "diagonal":  # each dimension its own D = 1 model: nu_0 = 3, nu_n = 3 + n
        nu0, nun = 3.0, 3.0 + n
        per_dim = (-0.5 * n * math.log(math.pi) + coef_term + 0.5 * nu0 * math.log(psi)
                   - 0.5 * nun * scatter.diagonal().log() + math.lgamma(nun / 2)
                   - math.lgamma(nu0 / 2))  # fmt: skip
        return per_dim.sum()
    nu0, nun = d + 2.0, float(dof)
    logdet = cholesky_logdet(torch.linalg.cholesky(scatter))
    return (-0.5 * n * d * math.log(math.pi) + d * coef_term + 0.5 * nu0 * d * math.log(psi)
            - 0.5 * nun * logdet + torch.special.multigammaln(scatter.new_tensor(nun / 2), d)
            - torch.special.multigammaln(scatter.new_tensor(nu0 / 2), d))  # fmt: skip


def student_t_predictive(
    u: torch.Tensor, precision_tril: torch.Tensor, coef: torch.Tensor, scatter: torch.Tensor,
    dof: torch.Tensor, noise: str, psi: float,
) -> tuple[float | torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """The Student-t posterior predictive of the target at inputs ``u [..., P]`` under one
    phase's posterior (``precision_tril`` the Cholesky factor of ``Lambda_n [P, P]``,
    ``coef [P, Dz]``, ``scatter [Dz, Dz]``, ``dof``; :func:`posterior`) and prior noise scale
    ``psi``: ``(df, loc [..., Dz], scale)``, ``scale`` a Cholesky factor ``[..., Dz, Dz]``
    (``"full"`` and ``"isotropic"`` noise) or per-dimension scales ``[..., Dz]``
    (``"diagonal"``)."""
    d = coef.shape[1]
    loc = u @ coef  # [..., Dz]
    # 1 + u^T Lambda_n^-1 u, with the Cholesky factor of Lambda_n
    flat = u.reshape(-1, u.shape[-1])
    v = torch.linalg.solve_triangular(precision_tril, flat.T, upper=False)
    inflate = (1.0 + v.pow(2).sum(0)).reshape(u.shape[:-1])
    nu = dof
    if noise == "full":
        tril = torch.linalg.cholesky(scatter / (nu - d + 1))
        return nu - d + 1, loc, tril * inflate[..., None, None].sqrt()
    if noise == "diagonal":
        # per dimension the Dz = 1 prior, with the same nu_n - Dz + 1 = 3 + n
        df = nu - d + 1
        return df, loc, (scatter.diagonal() / df).sqrt() * inflate[..., None].sqrt()
    # isotropic: sigma^2 ~ IG(2, psi): a_n = 2 + n Dz / 2, b_n = psi + tr(Psi_n - psi I) / 2
    n = nu - d - 2
    a_n = 2.0 + n * d / 2
    b_n = psi + 0.5 * (scatter.trace() - d * psi)
    eye = torch.eye(d, dtype=u.dtype, device=u.device)
    return 2 * a_n, loc, eye * (b_n / a_n * inflate)[..., None, None].sqrt()


def student_t_log_prob(
    x: torch.Tensor, df: float | torch.Tensor, loc: torch.Tensor, scale: torch.Tensor, noise: str
) -> torch.Tensor:
    """``[...]`` log density of ``x [..., Dz]`` under the predictive ``(df, loc, scale)`` of
    :func:`student_t_predictive` (a product of per-dimension Student-t for ``"diagonal"``
    noise). Not validated: rows that overflow the arithmetic give NaN or inf."""
    if noise == "diagonal":
        return StudentT(df, loc, scale, validate_args=False).log_prob(x).sum(-1)
    return MultivariateStudentT(df, loc, scale, validate_args=False).log_prob(x)


def student_t_sample(
    df: float | torch.Tensor, loc: torch.Tensor, scale: torch.Tensor, noise: str,
    generator: torch.Generator | None = None,
) -> torch.Tensor:  # fmt: skip
    """``[..., Dz]`` draws from the predictive ``(df, loc, scale)`` of
    :func:`student_t_predictive`: ``loc + L eps sqrt(df / chi2_df)`` with a chi-square per draw
    (per dimension for ``"diagonal"`` noise), drawn by NumPy from a seed that ``generator``
    draws, so a seeded generator gives the same draws."""
    draw_on = loc.device if generator is None else generator.device
    eps = torch.randn(loc.shape, generator=generator, dtype=loc.dtype, device=draw_on)
    eps = eps.to(loc.device)
    seed = int(torch.randint(2**62, (1,), generator=generator, device=draw_on))
    shape = loc.shape if noise == "diagonal" else loc.shape[:-1]
    chi2 = np.random.default_rng(seed).chisquare(float(df), size=tuple(shape))
    t_scale = (float(df) / torch.as_tensor(chi2, dtype=loc.dtype, device=loc.device)).sqrt()
    if noise == "diagonal":
        return loc + scale * eps * t_scale
    return loc + (scale @ eps[..., None])[..., 0] * t_scale[..., None]
