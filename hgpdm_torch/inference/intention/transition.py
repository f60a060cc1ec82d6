r"""Transition moments of the online filter: ``x_{t+1} | x_t, g_k`` for all K grid values at
one Gaussian ``q(x_t)`` per stream (Eq. 29-31 and ``Q^x`` of Sec. 3.3.1).

The online filter (and the Monte-Carlo planner on it) needs, for B input Gaussians
``x ~ N(mu_b, Sigma_b)`` and each intention value ``g_k``, the mean, covariance and ``Cov[x, x']``
of ``x' = f(x, g_k) + noise``. Two objects give them with the same interface
(:class:`TransitionMoments`):

- :class:`~hgpdm_torch.gp_shared.SharedTransition` (:meth:`GPPosterior.shared_moments
  <hgpdm_torch.gp.GPPosterior.shared_moments>`), the fast path for the IDDM's tensor-product
  kernel (one ``N x N`` expectation per stream for all K values);
- :class:`GenericTransition`, any transition kernel that :mod:`hgpdm_torch.expectations`
  supports (the H-GPDM's with its linear terms, a discrete kernel with ``sharing > 0``, a user
  kernel, a plain GPDM's without g): :meth:`GPPosterior.predict_gaussian
  <hgpdm_torch.gp.GPPosterior.predict_gaussian>` of the model's transition GP at ``[x, g_k]``
  with ``g_k`` known (zero variance).

:func:`transition_moments` picks one (``transition="auto"``: the fast path where the kernel
allows it), on the exact GP or on its sparse DTC approximation (``inducing``: the same
pseudo-inputs for both, :func:`~hgpdm_torch.gp_shared.sparse_posterior`). Both give the same
moments where both apply (``tests/inference/test_generic_transition.py``: 1e-8 in float64).

Shapes: ``B`` streams, ``K`` intention values, ``Dx`` latent, ``Dg`` intention dims (0 for a
GPDM), ``N`` transition training points.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Protocol

import torch

from ... import settings
from ...expectations import kernel_leaves, split_terms
from ...gp import GPPosterior
from ...gp_shared import SharedTransition, sparse_posterior
from ...models import GPDM
from ...moments import input_operations
from ...tiling import OpCount
from ...validation import check_choice
from .state_prior import marginal_state_prior

__all__ = [
    "EVIDENCE_LIMIT",
    "PRECISION_LIMIT",
    "TRANSITIONS",
    "GenericTransition",
    "TransitionMoments",
    "transition_moments",
]

#: The choices of :func:`transition_moments` (``OnlineIntentionFilter(transition=...)``).
TRANSITIONS = ("auto", "shared", "generic")


class TransitionMoments(Protocol):
    """What the online filter needs of its transition (``SharedTransition``,
    :class:`GenericTransition`).

    Attributes:
        values: ``[K, Dg]`` the intention grid, in the computation dtype.
        inputs: ``[N', Dx(+Dg)]`` training (or pseudo-) inputs in the computation dtype; their
            number sets the filter's default chunk size.
    """

    values: torch.Tensor
    inputs: torch.Tensor

    @property
    def num_values(self) -> int: ...

    def moments(
        self,
        mu: torch.Tensor,
        Sigma: torch.Tensor,
        phase: torch.Tensor | None = None,
        *,
        cross: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]: ...

    def operations(self, streams: int = 1, *, cross: bool = True) -> OpCount: ...

    def workspace(self) -> int: ...

    def compiled(self) -> bool: ...


class GenericTransition:
    r"""Transition moments for every K grid value by moment matching of the transition GP.

    For ``x ~ N(mu, Sigma)`` and each grid value ``g_k`` this is
    :meth:`GPPosterior.predict_gaussian <hgpdm_torch.gp.GPPosterior.predict_gaussian>` at the
    input ``[x, g_k]`` with ``g_k`` known (zero variance) and ``include_noise=True``, called once
    for all streams and values (``mu [B, 1, Dx]`` against ``g [1, K, Dg]``, so the ``x`` part of
    every kernel term is shared by the K values, and a discrete g touches only its own training
    points). Any kernel that :mod:`hgpdm_torch.expectations` supports works: the H-GPDM's RBF
    plus linear terms, the discrete kernel with ``sharing > 0``, a user's. A plain GPDM has no
    g (``values [1, 0]``): K = 1, and the filter is GP-ADF. A sparse posterior
    (:meth:`GPPosterior.sparse <hgpdm_torch.gp.GPPosterior.sparse>`) works the same way, on its
    M pseudo-inputs.

    A phase-aware IDDM's GP (``IDDM(phase_width=...)``) maps ``[x, g, p]``: with ``phase=True``
    each stream's phase ``p`` (its frame index) is one more known column, given to
    :meth:`moments`.

    Args:
        posterior: the transition GP ``[x, g] -> x_{t+1}`` (``model.transition_posterior()``),
            exact or sparse.
        values: ``[K, Dg]`` intention grid or codes (``[1, 0]`` for a model without g).
        dtype: computation dtype (default the posterior's; another one refactorises the GP in it).
        phase: whether the GP's last input column is the phase.
    """

    def __init__(
        self,
        posterior: GPPosterior,
        values: torch.Tensor,
        dtype: torch.dtype | None = None,
        *,
        phase: bool = False,
    ) -> None:
        dtype = dtype or posterior.train_inputs.dtype
        dg = values.shape[-1]
        if posterior.input_dim - dg - int(phase) != posterior.output_dim:
            what = "[x, g, p]" if phase else "[x, g]"
            raise ValueError(
                f"the transition GP maps {what} (Din = {posterior.input_dim}) to x "
                f"(Dx = {posterior.output_dim}); the grid has Dg = {dg} columns"
            )
        self.posterior = posterior.to_dtype(dtype)
        self.values = values.to(dtype)
        self.inputs = self.posterior.train_inputs
        self.phase = bool(phase)
        self._g = self.values[None] if dg else None  # [1, K, Dg]

    @property
    def num_values(self) -> int:
        """K."""
        return self.values.shape[0]

    def moments(
        self,
        mu: torch.Tensor,
        Sigma: torch.Tensor,
        phase: torch.Tensor | None = None,
        *,
        cross: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Moments of ``x_{t+1} = f(x, g_k) + noise`` for every k at ``x ~ N(mu, Sigma)``.

        Args:
            mu: ``[B, Dx]``; Sigma: ``[B, Dx, Dx]``.
            phase: ``[B]`` each stream's phase (the frame index of ``x``); required for, and
                only for, a phase-aware GP.
            cross: accepted for the protocol (the shared path skips ``Cov[x, x_{t+1}]`` without
                it); moment matching gives it with the others, so it is returned either way.

        Returns:
            ``mean [B, K, Dx]``, ``cov [B, K, Dx, Dx]`` and ``Cov[x, x_{t+1}] [B, K, Dx, Dx]``.
        """
        if (phase is None) == self.phase:
            raise ValueError(
                "this transition GP takes each stream's phase: pass phase [B]"
                if self.phase
                else "phase is for a phase-aware transition GP (IDDM(phase_width=...)) only"
            )
        with settings.internal_step():  # the caller's own Gaussians
            if phase is not None:
                p = phase.to(mu)[:, None, None].expand(-1, self.num_values, 1)
                g = p if self._g is None else torch.cat([self._g.expand(len(p), -1, -1), p], -1)
                return self.posterior.predict_gaussian(
                    mu[:, None], Sigma[:, None], g=g, include_noise=True
                )
            if self._g is None:  # no g: one value
                mean, cov, cross = self.posterior.predict_gaussian(mu, Sigma, include_noise=True)
                return mean[:, None], cov[:, None], cross[:, None]
            return self.posterior.predict_gaussian(
                mu[:, None], Sigma[:, None], g=self._g, include_noise=True
            )

    def workspace(self) -> int:
        """Entries of the fused path's work space per stream: one input's ``psi2`` (``N^2``)
        and its products with the K grid values' weights (``N K Dx``)."""
        n = self.inputs.shape[0]
        return n * n + n * self.num_values * self.posterior.output_dim

    def compiled(self) -> bool:
        """``False``: the generic moments run in torch (their exponential may be the compiled
        one, :func:`hgpdm_torch.tiling.exp_`)."""
        return False

    def operations(self, streams: int = 1, *, cross: bool = True) -> OpCount:
        """Work of :meth:`moments` per stream when ``streams`` share a call (the floor's
        count; ``cross`` does not change it): the moment matching of the transition GP for the
        K grid values sharing one input Gaussian (:func:`~hgpdm_torch.moments.input_operations`);
        with a discrete g's blocks (:meth:`GPPosterior.blocks
        <hgpdm_torch.gp.GPPosterior.blocks>`) K separate ones over the padded block of each
        code."""
        post = self.posterior
        dx, X = post.output_dim, post.train_inputs
        leaves = kernel_leaves(post.kernel, post.input_dim)
        g = None if self._g is None else self._g[0]
        if self.phase:  # the phase is one more known column (its value does not matter here)
            p = X.new_zeros(self.num_values, 1)
            g = p if g is None else torch.cat([g, p], -1)
        blocks = post.blocks() if g is not None else None
        if blocks is None:
            terms = split_terms(leaves, X, g, dx)
            return input_operations(terms, X.shape[0], dx, sets=self.num_values, inputs=streams)
        Xb = blocks[0][0, :, :dx]  # one code's padded block: [M, Dx]
        x_leaves = [replace(lf, weight=lf.weight[:dx], codes=()) for lf in leaves]
        terms = split_terms(x_leaves, Xb, None, dx)
        return input_operations(terms, Xb.shape[0], dx, inputs=streams) * self.num_values


def transition_moments(
    posterior: GPPosterior,
    values: torch.Tensor,
    dtype: torch.dtype | None = None,
    *,
    transition: str = "auto",
    inducing: int | None = None,
    inducing_values: int | None = None,
    phase: bool = False,
) -> TransitionMoments:
    """The transition moments object for this GP and grid.

    Args:
        posterior: the transition GP (``model.transition_posterior()``).
        values: ``[K, Dg]`` intention grid (``[1, 0]`` without g).
        dtype: computation dtype.
        transition: ``"shared"`` (:meth:`GPPosterior.shared_moments
            <hgpdm_torch.gp.GPPosterior.shared_moments>`, a :class:`SharedTransition`;
            ``TypeError`` unless the kernel is the IDDM's), ``"generic"``
            (:class:`GenericTransition`), or ``"auto"``: shared where
            :meth:`SharedTransition.supports` the kernel, else generic.
        inducing: number of pseudo-inputs M of a sparse (DTC) transition GP on either path
            (:func:`~hgpdm_torch.gp_shared.sparse_posterior`), or ``None`` for the exact GP.
        inducing_values: its distinct intention values (continuous g; see there).
        phase: the GP's last input column is the phase (``IDDM(phase_width=...)``), given to
            ``moments`` per stream; either path on the exact GP (``inducing`` is refused: its
            pseudo-inputs are built over ``[x, g]``), the shared one where the kernel is the
            IDDM's tensor product with the phase factor.
    """
    check_choice(transition, "transition", TRANSITIONS)
    if phase and inducing is not None:
        raise ValueError(
            "a phase-aware transition GP (IDDM(phase_width=...)) runs on the exact GP: its "
            "pseudo-inputs would be built over [x, g] without the phase; use inducing=None"
        )
    if transition == "auto":
        shared = SharedTransition.supports(posterior, values, phase)
        transition = "shared" if shared else "generic"
    if phase:
        if transition == "shared":
            return SharedTransition(posterior, values, dtype, phase=True)
        return GenericTransition(posterior, values, dtype, phase=True)
    posterior = sparse_posterior(posterior, values.shape[-1], inducing, inducing_values)
    if transition == "shared":
        return posterior.shared_moments(values, dtype)
    return GenericTransition(posterior, values, dtype)


#: Largest rounding error of the transition moments in a filter's dtype, relative to the
#: predictive spread, that :class:`OnlineIntentionFilter` accepts for a dtype other than its
#: model's. Measured in float32: 0.03-1.2 on models whose float32 beliefs stay within 0.05 of
#: float64 on streams like the training ones, ~1.4e3 with alpha-bar (alpha_4 = 1e-4), whose
#: streams fail within a few updates. This check catches that breakdown; the accuracy of the
#: beliefs is :data:`EVIDENCE_LIMIT`'s.
PRECISION_LIMIT = 10.0

#: Largest rounding error, in nats, of the per-step evidence ``log q(z_t | g)`` (its differences
#: between grid values: the part that moves the belief) that :class:`OnlineIntentionFilter`
#: accepts for a dtype other than its model's. A near tie of two values moves by about a quarter
#: of the error per step, and a stream far from the training data (an unseen class) makes large
#: innovations that multiply the error of the predictive moments. Measured in float32 on
#: IDDMs (discrete, 3 classes; continuous) against the largest float64 belief difference over
#: held-out and unseen-class streams: 6e-4 nats -> 2e-4, 0.044 -> 0.006, 0.71 -> 0.032,
#: 1.6 -> 0.044, 8 -> 1.0 (linear measurement, alpha_4 = 0.2 ... 1e-2); an RBF measurement GP
#: errs by 20-2000 nats -> 1.0.
EVIDENCE_LIMIT = 0.1


def _evidence_spread(ll: torch.Tensor, ref: torch.Tensor) -> float:
    """Largest ``max_k - min_k`` of ``ll - ref`` over the probes ``[..., K]`` (NaN -> inf)."""
    d = ll.to(ref.dtype) - ref
    err = float((d.amax(-1) - d.amin(-1)).max())
    return err if err == err else float("inf")


def check_precision(
    model: GPDM,
    reference: TransitionMoments,
    low: TransitionMoments,
    measure_ref: Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
    measure_low: Callable[..., tuple[torch.Tensor, torch.Tensor, torch.Tensor]],
) -> None:
    """Refuse ``low``'s dtype where it is not accurate enough for this model.

    At 8 training latents, with the latents' covariance scaled by 1, 1e-2 and 1e-4:

    1. the transition moments must differ from ``reference``'s by at most
       :data:`PRECISION_LIMIT` times the smallest predictive standard deviation (means) or
       variance (covariances);
    2. the evidence of the predictive step, ``log q(z | g_k)`` by ``measure_ref`` /
       ``measure_low`` (the measurement updates in the two dtypes) for the observation of the
       next frame and for that of a distant one (a large innovation, as an unseen class makes),
       must differ between grid values from the reference's by at most :data:`EVIDENCE_LIMIT`
       nats (the filter's evidence: ``low``'s moments through ``measure_low``). The message
       names the measurement GP as the cause where its update alone errs by half of that.
    """
    ref_dtype, low_dtype = reference.inputs.dtype, low.inputs.dtype
    x = model.latent.detach().to(ref_dtype)
    n = x.shape[0]
    idx = torch.linspace(0, n - 1, min(8, n), device=x.device).round().long()
    _, spread = marginal_state_prior(model, None, None, x.dtype)  # the training latents' covariance
    worst = 0.0
    probes = []
    phase = None  # a phase-aware GP's probes at their training frames' phases
    if getattr(reference, "phase", False):
        seq = torch.searchsorted(model.first_index, idx, right=True) - 1
        phase = (idx - model.first_index[seq]).to(ref_dtype)
    for scale in (1.0, 1e-2, 1e-4):
        mu, P = x[idx], (scale * spread).expand(len(idx), -1, -1)
        m_ref, c_ref, _ = reference.moments(mu, P, phase, cross=False)
        low_phase = None if phase is None else phase.to(low_dtype)
        m_low, c_low, _ = low.moments(mu.to(low_dtype), P.to(low_dtype), low_phase, cross=False)
        var = torch.linalg.eigvalsh(c_ref)[..., 0].clamp_min(torch.finfo(c_ref.dtype).tiny)
        err_c = (c_low.to(c_ref.dtype) - c_ref).abs().amax((-1, -2)) / var
        err_m = (m_low.to(m_ref.dtype) - m_ref).abs().amax(-1) / var.sqrt()
        worst = max(worst, float(err_c.max()), float(err_m.max()))
        probes.append((m_ref, c_ref, m_low, c_low))
    name, own = (str(d).removeprefix("torch.") for d in (low_dtype, ref_dtype))
    if not worst <= PRECISION_LIMIT:
        raise ValueError(
            f"dtype={name} is not accurate enough for this model: its rounding error in the "
            f"transition moments is {worst:.3g} times the predictive spread (limit "
            f"{PRECISION_LIMIT}), because the weights (K + alpha_4 I)^-1 are too large for its "
            f"digits (process noise alpha_4 = {float(model.transition_noise.detach()):.3g}); use "
            f"the model's dtype ({own}), or a model with a larger alpha_4"
        )
    # the evidence of every probe for the next frame's observation and a distant frame's
    m_ref, c_ref, m_low, c_low = (torch.cat([p[i] for p in probes])[:, :, None] for i in range(4))
    nxt = torch.where(torch.isin(idx, model.src_index), idx + 1, idx)
    rows = torch.stack([nxt, (nxt + n // 2) % n], -1).repeat(len(probes), 1)  # [P, 2]
    z = model.observations.detach().to(ref_dtype)[rows][:, None]  # [P, 1, 2, Dz]
    with settings.internal_step():  # the filter's own kind of Gaussians
        ll = measure_ref(m_ref, c_ref, z)[2]  # [P, K, 2]
        z_low = z.to(low_dtype)
        ll_meas = measure_low(m_ref.to(low_dtype), c_ref.to(low_dtype), z_low)[2]
        ll_low = measure_low(m_low, c_low, z_low)[2]  # as the filter computes it
    dims = (0, 2, 1)  # grid values last
    err = _evidence_spread(ll_low.permute(dims), ll.permute(dims))
    err_meas = _evidence_spread(ll_meas.permute(dims), ll.permute(dims))
    if not err <= EVIDENCE_LIMIT:
        # a part is named where it fails the limit on its own (the measurement GP with exact
        # transition moments) or at least doubles the error (the transition GP): a fixed
        # threshold, not a comparison of two errors whose ratio moves with the rounding
        meas = (
            "measurement GP, whose weights (K + sigma^2 I)^-1 are too large for its digits "
            f"(observation noise sigma^2 = {float(model.measurement_noise.detach()):.3g})"
        )
        trans = (
            "transition GP, whose weights (K + alpha_4 I)^-1 are too large for its digits "
            f"(process noise alpha_4 = {float(model.transition_noise.detach()):.3g})"
        )
        meas_bad, trans_bad = err_meas > EVIDENCE_LIMIT, not err_meas > err / 2
        if meas_bad and trans_bad:
            cause, fix = f"{meas}, and from the {trans}", "observation noise and alpha_4"
        elif meas_bad:
            cause, fix = meas, "observation noise"
        else:
            cause, fix = trans, "alpha_4"
        raise ValueError(
            f"dtype={name} is not accurate enough for this model: its rounding error in the "
            f"evidence log q(z_t | g) differs between intention values by up to {err:.3g} nats "
            f"(limit {EVIDENCE_LIMIT}; {err_meas:.3g} with exact transition moments), enough "
            f"to flip a near-tied belief; most of it comes from the {cause}; use the model's "
            f"dtype ({own}), or a model with a larger {fix}"
        )
