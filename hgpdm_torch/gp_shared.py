r"""Moment matching of a GP at one input Gaussian shared by K values of its known input columns.

The IDDM transition GP maps ``[x, g] -> x_{t+1}`` with the kernel
``alpha_1 exp(-alpha_2/2 |x - x'|^2) phi(g, g')`` (``phi`` an RBF in g, or ``delta`` for a
discrete g). The online filter needs its moments at one input Gaussian ``q(x)`` per stream for
all K values of an intention grid, so the ``N x N`` expectation ``psi2`` over ``x`` is computed
once per stream and step; and as ``g`` is constant within a training sequence, the N training
points form U groups of equal ``g``. All K second moments and traces then follow from ``U x U``
group sums of ``psi2``: ``beta_k^T psi2 beta_k = sum_uv phi_ku phi_kv (beta_u^T psi2_uv beta_v)``,
with no ``N x N`` work per value. :class:`SharedTransition` does this
(:meth:`GPPosterior.shared_moments <hgpdm_torch.gp.GPPosterior.shared_moments>`), optionally on
M < N pseudo-inputs (:func:`sparse_posterior`, Sec. 3.3.3: :meth:`GPPosterior.sparse
<hgpdm_torch.gp.GPPosterior.sparse>` on pseudo-inputs that share few values of g), and for a
phase-aware IDDM (inputs ``[x, g, p]``), whose phase factor rescales each training point per
stream. ``psi2`` is contracted tile by tile without being stored for all streams (the fused
path, :mod:`hgpdm_torch.tiling`) or formed for all of them (the materialised path,
:class:`~hgpdm_torch.settings.moment_path`). Other kernels take :meth:`GPPosterior.predict_gaussian
<hgpdm_torch.gp.GPPosterior.predict_gaussian>`.

Shapes: ``B`` streams, ``K`` grid values, ``Dx`` latent, ``Dg`` intention dims, ``N`` training
points, ``M`` pseudo-inputs.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from . import native, settings
from .expectations import (
    Leaf,
    Term,
    kernel_leaves,
    rbf_psi1_quadratic,
    rbf_psi2_exponent,
    rbf_psi2_quadratic,
    split_terms,
    term_psi1,
    term_psi1_grad,
    term_psi2,
)
from .linalg import symmetrize
from .tiling import OpCount, differentiable_tile, exp_, keeps_tiles, per_tile

if TYPE_CHECKING:  # gp.py imports this module: GPPosterior only annotates here
    from .gp import GPPosterior

__all__ = ["SharedTransition", "sparse_posterior"]


@dataclass(frozen=True)
class _NativeLayout:
    """The compiled kernel's column layout of a :class:`SharedTransition` (module
    :mod:`hgpdm_torch.native`): columns in the order ``(m, v)`` with v padded to ``up``."""

    cols: torch.Tensor  # [Np] point of each column (padding: point 0, zero weights)
    beta: torch.Tensor  # [N, Dx] each row's weights
    betac: torch.Tensor  # [Dx, Np] each column's weights (0 at padding)
    kinv: torch.Tensor  # [N, Np]
    phi_t: torch.Tensor  # [up, Kp] phi[k, v], 0 at padding v and k >= K
    up: int
    pairs: tuple[torch.Tensor, torch.Tensor]  # weight dims (a, b), a <= b, row-major


def _positive_int(value: object, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is an int >= 1 (not a bool)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be a positive int or None, got {value!r}")


def sparse_posterior(
    posterior: GPPosterior, dg: int, inducing: int | None, inducing_values: int | None = None
) -> GPPosterior:
    """The transition GP on ``inducing`` pseudo-inputs (DTC, Sec. 3.3.3), or ``posterior``.

    The pseudo-inputs are training latents paired with ``inducing_values`` distinct values of
    the last ``dg`` input columns (K-means centres of the training g; all codes of a discrete
    g; none without g), so that :class:`SharedTransition` on the result has that many groups:
    its work per step falls from ``O(N^2 Dx + K U N Dx)`` to ``O(M^2 Dx + K inducing_values M
    Dx)``. Both transition paths of the online filter use this choice, so they agree.

    Args:
        posterior: the exact GP over ``[x, g]`` (``Din = Dx + dg``).
        dg: number of trailing intention columns ``Dg`` (0 without g).
        inducing: number of pseudo-inputs M, or ``None`` for ``posterior`` itself.
        inducing_values: distinct intention values among the pseudo-inputs for a continuous g,
            at most M (default ``round(sqrt(M))``, or all training values when ``M >= N``: all
            training inputs, the exact GP but for the ridge that
            :meth:`GPPosterior.sparse <hgpdm_torch.gp.GPPosterior.sparse>` adds to an
            ill-conditioned ``K_MM``).

    Returns:
        ``posterior.sparse(Z)`` with ``Z [<= M, Din]`` (more than M only when M is below the
        number of discrete codes), or ``posterior`` when ``inducing`` is ``None``.

    Raises:
        ValueError: ``inducing``/``inducing_values`` not positive ints, ``inducing_values``
            above ``inducing`` or without it; a posterior with a noise per value (see
            :meth:`GPPosterior.sparse <hgpdm_torch.gp.GPPosterior.sparse>`).
    """
    if inducing is None:
        if inducing_values is not None:
            raise ValueError("inducing_values needs inducing (the number of pseudo-inputs)")
        return posterior
    _positive_int(inducing, "inducing")
    if inducing_values is not None:
        _positive_int(inducing_values, "inducing_values")
        if inducing_values > inducing:
            raise ValueError(
                f"inducing_values ({inducing_values}) cannot exceed inducing ({inducing}): "
                "each intention value needs at least one pseudo-input"
            )
    X = posterior.train_inputs
    if not 0 <= dg < X.shape[1]:
        raise ValueError(f"dg must be in [0, {X.shape[1] - 1}] (Din - 1), got {dg}")
    discrete = any(leaf.codes for leaf in kernel_leaves(posterior.kernel, X.shape[1]))
    dx = X.shape[1] - dg
    return posterior.sparse(_pseudo_inputs(X, dx, inducing, inducing_values, discrete))


def _pseudo_inputs(
    X: torch.Tensor, dx: int, m: int, num_values: int | None, discrete: bool
) -> torch.Tensor:
    """M pseudo-inputs ``[<= M, Dx + Dg]`` for the sparse transition GP (Sec. 3.3.3).

    The cost per step grows with the number of distinct intention values among the pseudo-inputs
    (the groups of :class:`SharedTransition`), so they share ``num_values`` values: the training
    intentions' K-means centres, weighted by their number of points (default
    ``round(sqrt(M))``; the training values themselves when ``M >= N``: all training inputs;
    a discrete g always keeps its codes). Each value gets ``floor(M / values)`` (at least one)
    training latents of its cluster, evenly spread over the cluster's points (all of them when
    it has fewer), so there are at most M unless M is below the number of discrete codes.
    Without g (``Dg = 0``) the M latents are evenly spread over all training points.
    """
    if X.shape[1] == dx:  # no g: one value shared by all points
        uniq = X.new_zeros(1, 0)
        group = torch.zeros(X.shape[0], dtype=torch.long, device=X.device)
    else:
        uniq, group = torch.unique(X[:, dx:], dim=0, return_inverse=True)
    u = len(uniq)
    if num_values is None:
        num_values = max(1, round(math.sqrt(m))) if m < X.shape[0] else u
    if discrete or num_values >= u:
        if m >= X.shape[0]:  # every value kept and room for every point: the exact GP's inputs
            return X
        centres, cluster = uniq, group
    else:
        from sklearn.cluster import KMeans  # only here: importing sklearn takes ~1 s

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


def _group_terms(
    leaves: list[Leaf], X: torch.Tensor, values: torch.Tensor, dx: int
) -> tuple[torch.Tensor, torch.Tensor, list[Term]]:
    """The distinct ``g`` of the inputs ``X [N, Dx + Dg]`` (``[U, Dg]``), each point's group
    ``[N]``, and the kernel's terms split at them (factors ``[K, U]`` for the grid ``values``)."""
    uniq, group = torch.unique(X[:, dx:], dim=0, return_inverse=True)
    terms = split_terms(leaves, torch.cat([uniq.new_zeros(len(uniq), dx), uniq], 1), values, dx)
    return uniq, group, terms


def _phase_split(
    leaves: list[Leaf], X: torch.Tensor, phase: bool
) -> tuple[list[Leaf], torch.Tensor, torch.Tensor | None, torch.Tensor | None] | None:
    """Leaves and inputs over ``[x, g]``, each point's phase ``[N]`` and the phase precision
    ``w_p``: for a phase-aware GP over ``[x, g, p]`` whose kernel is one RBF leaf (the IDDM's
    tensor product with ``exp(-w_p (p - p')^2 / 2)``), that leaf without its phase column;
    ``None`` where the kernel has another form. Without ``phase``: the leaves and inputs as they
    are."""
    if not phase:
        return leaves, X, None, None
    if len(leaves) != 1 or leaves[0].kind != "rbf" or leaves[0].factors:
        return None
    (leaf,) = leaves
    last = X.shape[1] - 1
    if last in leaf.codes:
        return None
    plain = replace(leaf, weight=leaf.weight[:last], cols=leaf.cols - {last})
    return [plain], X[:, :last], X[:, last], leaf.weight[last]


def _tensor_product(terms: list[Term]) -> bool:
    """Whether the kernel is one RBF over ``x`` times a factor of ``g`` (the IDDM form)."""
    return len(terms) == 1 and terms[0].kind == "rbf" and terms[0].factor is not None


def _check_values(posterior: GPPosterior, values: torch.Tensor, phase: bool = False) -> None:
    """``values`` must be a ``[K, Dg]`` tensor of trailing input columns (before the phase),
    ``1 <= Dg < Din``."""
    if not isinstance(values, torch.Tensor):
        raise TypeError(f"values must be a tensor [K, Dg], got {type(values).__name__}")
    din = posterior.input_dim - int(phase)
    if values.dim() != 2 or not 1 <= values.shape[1] < din:
        raise ValueError(
            f"values must be [K, Dg] with 1 <= Dg < Din = {din} (the trailing input columns), "
            f"got {tuple(values.shape)}"
        )


class SharedTransition:
    r"""Moment matching of the IDDM transition GP at one input Gaussian for all K intentions.

    For ``x ~ N(mu, Sigma)`` and each grid value ``g_k`` this gives exactly what
    :meth:`GPPosterior.predict_gaussian <hgpdm_torch.gp.GPPosterior.predict_gaussian>` gives for
    ``[x, g_k]`` with ``include_noise=True`` (mean, covariance and ``Cov[x, f]``, Eq. 29-31 and
    ``Q^x``; with the posterior's ``scale`` and ``offset``), organised for speed:

    - the kernel must be one RBF term over ``x`` times a factor of ``g`` (the IDDM tensor product
      ``iddm_continuous`` or the block kernel ``iddm_discrete``); the ``x`` expectations
      ``psi1, E[grad k], psi2`` come from :mod:`hgpdm_torch.expectations`;
    - the training points are grouped by their ``g`` (U groups; padded to a common size L, with
      zero weights on the padding), and ``phi [K, U]`` holds the ``g`` factor of grid value k
      and group u. The second moments contract ``psi2`` with each group's weights, then with
      ``phi``: ``O(N^2 Dx + K U N Dx)`` per stream instead of ``O(K N^2 Dx)``.

    It reads the posterior's ``train_inputs``, ``weights`` and ``kinv`` only, so a sparse
    posterior (:meth:`GPPosterior.sparse <hgpdm_torch.gp.GPPosterior.sparse>`) works as well,
    its pseudo-inputs grouped instead of the training points. With ``inducing = M`` the
    constructor builds that sparse GP itself (the deterministic training conditional, DTC, of
    thesis Sec. 3.3.3: with ``A = noise K_MM + K_MN K_NM`` the mean weights become
    ``A^-1 K_MN Y`` and ``K^-1`` in the variance becomes ``K_MM^-1 - noise A^-1``) on the
    pseudo-inputs of :func:`sparse_posterior`, whose ``inducing_values`` intention values become
    the groups: the work per step falls to ``O(M^2 Dx + K inducing_values M Dx)``.

    Args:
        posterior: the transition GP ``[x, g] -> x_{t+1}`` (``model.transition_posterior()``).
        values: ``[K, Dg]`` intention grid (or codes), ``1 <= Dg < Din``.
        dtype: computation dtype (the posterior's weights and ``K^-1`` are cast from it).
        inducing: number of pseudo-inputs M (``None``: ``posterior`` as it is).
        inducing_values: number of distinct intention values among the pseudo-inputs for a
            continuous g, at most M (default ``round(sqrt(M))``, or all training values when
            ``M >= N``).
        phase: the GP's last input column is the phase of a phase-aware IDDM
            (``IDDM(phase_width=...)``, inputs ``[x, g, p]``): its factor
            ``exp(-w_p (p - p_i)^2 / 2)`` rescales every training point per stream, so the
            groups stay those of g and :meth:`moments` takes each stream's phase (exact GP only).
    """

    def __init__(
        self,
        posterior: GPPosterior,
        values: torch.Tensor,
        dtype: torch.dtype | None = None,
        *,
        inducing: int | None = None,
        inducing_values: int | None = None,
        phase: bool = False,
    ) -> None:
        _check_values(posterior, values, phase)
        dtype = dtype or posterior.train_inputs.dtype
        if phase and inducing is not None:
            raise ValueError("a phase-aware transition GP has no sparse (inducing) variant")
        posterior = sparse_posterior(posterior, values.shape[1], inducing, inducing_values)
        X = posterior.train_inputs
        dx = X.shape[1] - values.shape[1] - int(phase)
        if dx != posterior.output_dim:
            raise ValueError(
                f"the transition GP has Din = {X.shape[1]} input columns, not x (Dx = "
                f"{posterior.output_dim}), g (Dg = {values.shape[1]})"
                + (" and the phase" if phase else "")
                + (": a phase-aware GP (IDDM(phase_width=...)) needs phase=True" if not phase
                   and dx == posterior.output_dim + 1 else "")
            )  # fmt: skip
        split = _phase_split(kernel_leaves(posterior.kernel, X.shape[1]), X, phase)
        if split is None:
            raise TypeError(
                "SharedTransition with a phase needs the phase-aware IDDM kernel (one RBF over "
                "[x, g, p]); this kernel runs on GenericTransition"
            )
        leaves, X, point_phase, phase_weight = split
        weights, kinv = posterior.weights, posterior.kinv
        uniq, group, terms = _group_terms(leaves, X, values, dx)
        if not _tensor_product(terms):
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
        # a phase-aware GP: each padded point's phase [U L] and the phase precision w_p
        self.phase, self.phases, self.phase_weight = bool(phase), None, None
        if phase:
            self.phases = torch.cat([point_phase, point_phase.new_zeros(1)])[flat].to(dtype)
            self.phase_weight = phase_weight.detach().to(dtype)
        # phi_k(u_n) beta_n for every grid value k and padded point n: [K, U L, Dx]
        self.weighted_beta = (self.phi[:, :, None, None] * self.beta).reshape(len(values), -1, dx)
        # the fused path's columns in the order (m, v), point m of group v, so that the group
        # sums of a [rows (u, l), cols (m, v)] tile are one reduction over a middle dim
        self.columns = torch.arange(u_count * size, device=X.device).view(u_count, size).T
        self.columns = self.columns.reshape(-1)
        self.kinv_cols = self.kinv[:, self.columns].contiguous()  # [U L, L U]
        self.weighted_beta_cols = self.weighted_beta[:, self.columns].contiguous()  # [K, L U, Dx]
        self.beta_rows = self.beta.transpose(1, 2).contiguous()  # [U, Dx, L]
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
        # a transition GP has neither (None skips the no-op arithmetic on the hot path)
        scale2, offset = posterior.scale.pow(2), posterior.offset
        self.scale2 = None if bool((scale2 == 1).all()) else scale2.to(dtype)  # [Dx]
        self.offset = None if bool((offset == 0).all()) else offset.to(dtype)  # [Dx]

    @property
    def num_values(self) -> int:
        """K."""
        return self.phi.shape[0]

    @staticmethod
    def supports(posterior: GPPosterior, values: torch.Tensor, phase: bool = False) -> bool:
        """Whether the kernel of ``posterior`` has the form this class needs (one RBF term over
        ``x`` times a factor of ``g``: ``iddm_continuous``, or ``iddm_discrete`` without
        sharing) for the grid ``values [K, Dg]`` (``Dg >= 1``).

        Raises:
            TypeError: a kernel that :mod:`hgpdm_torch.expectations` does not support at all.
        """
        if values.shape[-1] == 0:  # no g: nothing to share between intentions
            return False
        X = posterior.train_inputs
        dx = X.shape[1] - values.shape[1] - int(phase)
        if dx != posterior.output_dim:  # other known columns than g (and the phase)
            return False
        split = _phase_split(kernel_leaves(posterior.kernel, X.shape[1]), X, phase)
        if split is None:
            return False
        return _tensor_product(_group_terms(split[0], split[1], values, dx)[2])

    def moments(
        self,
        mu: torch.Tensor,
        Sigma: torch.Tensor,
        phase: torch.Tensor | None = None,
        *,
        cross: bool = True,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Moments of ``x_{t+1} = f(x, g_k) + noise`` for every k at ``x ~ N(mu, Sigma)``
        (``noise``: alpha_4, or the ``alpha_4,k`` of value k with a per-value process noise).

        Args:
            mu: ``[B, Dx]``; Sigma: ``[B, Dx, Dx]``.
            phase: ``[B]`` each stream's phase (the frame index of ``x``); required for, and
                only for, a phase-aware GP (``phase=True``). Its factor
                ``exp(-w_p (p - p_i)^2 / 2)`` rescales each training point's weight per stream,
                so it multiplies ``psi1`` and ``E[grad k]`` and enters ``psi2``'s exponent.
            cross: whether to compute ``Cov[x, x_{t+1}]`` (and ``E[grad k]`` for it); the
                predictive filter step and the planner's particles do not use it.

        Returns:
            ``mean [B, K, Dx]``, ``cov [B, K, Dx, Dx]`` and ``Cov[x, x_{t+1}] [B, K, Dx, Dx]``
            (``None`` with ``cross=False``).
        """
        if (phase is None) != (self.phases is None):
            raise ValueError(
                "this transition GP takes each stream's phase: pass phase [B]"
                if self.phases is not None
                else "phase is for a phase-aware transition GP (IDDM(phase_width=...)) only"
            )
        b, dx, U, L = mu.shape[0], self.dx, self.groups, self.group_size
        log_phase = None
        if phase is not None:  # log of each point's phase factor per stream: [B, UL]
            log_phase = self.log_phase(phase.to(mu))
        fused = settings.moment_path.get() == "fused"
        inputs = (mu, Sigma) if log_phase is None else (mu, Sigma, log_phase)
        compiled = fused and self._native_ready(*inputs)
        if compiled:  # psi1 and the second moments in one call of the kernel
            p1, trace, second = self._native_moments(mu, Sigma, log_phase)
        grad = None
        if cross or not compiled:
            if cross:
                p1, grad = term_psi1_grad(self.term, mu, Sigma, self.inputs)  # [B, UL], [B, Dx, UL]
            else:
                p1 = term_psi1(self.term, mu, Sigma, self.inputs)
            if log_phase is not None:
                factor = log_phase.exp()
                p1 = p1 * factor
                grad = None if grad is None else grad * factor[:, None, :]
        phi, beta = self.phi, self.beta
        m_u = torch.einsum("bul,ula->bua", p1.view(b, U, L), beta)
        mean = torch.einsum("ku,bua->bka", phi, m_u)
        cov_x = None
        if grad is not None:
            g_u = torch.einsum("bdul,ula->bdua", grad.view(b, dx, U, L), beta)
            cov_x = Sigma[:, None] @ torch.einsum("ku,bdua->bkda", phi, g_u)
        if compiled:
            cov = second - mean[..., :, None] * mean[..., None, :]
        elif fused:
            trace, cov = self._fused_second(mu, Sigma, mean, log_phase)
        else:
            T, cov = self._materialised_second(mu, Sigma, p1, log_phase)
            trace = self._trace(T)
        var = (self.coef - trace).clamp_min(0.0) + self.noise
        var = (
            var[..., None].expand(b, -1, dx)
            if self.scale2 is None
            else var[..., None] * self.scale2
        )
        cov = symmetrize(cov) + torch.diag_embed(var)
        return mean if self.offset is None else mean + self.offset, cov, cov_x

    def _materialised_second(
        self,
        mu: torch.Tensor,
        Sigma: torch.Tensor,
        p1: torch.Tensor,
        log_phase: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Group sums ``T [B, U, U]`` of ``psi2 * K^-1`` and ``beta_k^T (psi2 - psi1 psi1^T)
        beta_k [B, K, Dx, Dx]`` with ``psi2`` formed for all B inputs (the materialised path;
        ``log_phase [B, UL]`` the log phase factors, if any)."""
        b, dx, U, L = mu.shape[0], self.dx, self.groups, self.group_size
        q = term_psi2(self.term, self.term, mu, Sigma, self.inputs)  # [B, UL, UL]
        if log_phase is not None:
            factor = log_phase.exp()
            q = q * factor[:, :, None] * factor[:, None, :]
        T = (q * self.kinv).view(b, U, L, U, L).sum(2).sum(-1)  # [B, U, U]; strided sum first
        # Cov[f] = beta_k^T (psi2 - psi1 psi1^T) beta_k: centring the N x N matrix first keeps
        # float32 usable (beta is large when the noise is small) and gives the covariance
        # without the cancellation of second moment minus squared mean.
        q = torch.baddbmm(q, p1[:, :, None], p1[:, None, :], alpha=-1.0)
        # sum_uv phi_ku phi_kv beta_u^T q_uv beta_v: contract each group's weights
        # (block-sparse, O(N^2 Dx)), then phi over groups, then the rows
        P1 = self.beta.transpose(1, 2) @ q.view(b, U, L, U * L)  # [B, U, Dx, UL]
        P2 = (self.phi @ P1.reshape(b, U, dx * U * L)).view(b, -1, dx, U * L)  # [B, K, Dx, UL]
        return T, P2 @ self.weighted_beta

    def _trace(self, T: torch.Tensor) -> torch.Tensor:
        """``tr(K^-1 psi2)`` of every value k, ``sum_uv phi_ku T_uv phi_kv`` ``[B, K]``, from the
        group sums ``T [B, U, U]``."""
        return ((self.phi @ T) * self.phi).sum(-1)

    def _fused_second(
        self,
        mu: torch.Tensor,
        Sigma: torch.Tensor,
        mean: torch.Tensor,
        log_phase: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """What :meth:`_materialised_second` gives, one tile of streams at a time, with the
        group sums ``T`` already reduced to the traces ``[B, K]`` (:meth:`_trace`).

        A tile is ``psi2 = exp(left @ right)`` of :func:`~hgpdm_torch.tiling.per_tile` streams,
        its rows in groups ``(u, l)`` and its columns in the order ``(m, v)`` (``columns``),
        reduced at once into buffers reused by every tile: the group weights (``[U, Dx, N]``),
        phi over groups (``[K, Dx, N]``) and the weighted columns give ``beta_k^T psi2 beta_k``;
        then, in place, the product with ``K^-1`` and one sum over the middle dim ``(l, m)`` give
        ``T``. The covariance is centred afterwards, ``- mean_k mean_k^T`` (``mean_k = beta_k^T
        psi1``): in float32 this errs about twice as much as centring ``psi2`` itself (0.06
        against 0.03 of the smallest predictive variance on the benchmark's IDDM, limit 10) and
        saves a pass over every tile. Under autograd the tiles are kept for the backward pass
        while they are small in all (:func:`~hgpdm_torch.tiling.keeps_tiles`), else each is
        recomputed there.
        """
        b, dx, U, L = mu.shape[0], self.dx, self.groups, self.group_size
        n, K = U * L, self.num_values
        left, right = rbf_psi2_exponent(self.term, self.term, mu, Sigma, self.inputs)
        if log_phase is not None:  # psi2_ij times both points' phase factors: in the exponent
            left[..., dx] += log_phase  # the row term (left and right are this call's own)
            right[..., dx + 1, :] += log_phase  # the column term
        right = right[..., self.columns]
        size = per_tile(self.workspace(), mu.dtype, mu.device)
        needs = (left, right, self.beta_rows, self.phi, self.kinv_cols, self.weighted_beta_cols)
        # the inputs' gradient, or the GP's (a posterior with detach=False): differentiable tiles,
        # kept for backward while small, else recomputed there (tiling)
        if torch.is_grad_enabled() and any(t.requires_grad for t in needs):
            keep = keeps_tiles(b * n * n, mu.dtype)
            parts = [
                differentiable_tile(self._tile, left[i : i + size], right[i : i + size], keep=keep)
                for i in range(0, b, size)
            ]
            T, second = (torch.cat([p[j] for p in parts]) for j in (0, 1))
        else:  # one set of buffers for all tiles; a tile's results go straight out
            new = mu.new_empty
            size = max(1, min(size, b))  # b = 0: no tile
            bufs = (new(size, n, n), new(size, U, dx, n), new(size, K, dx, n))
            T, second = new(b, U, U), new(b, K, dx, dx)
            for i in range(0, b, size):
                rows = slice(i, min(i + size, b))
                self._tile(left[rows], right[rows], out=(T[rows], second[rows]), bufs=bufs)
        return self._trace(T), second - mean[..., :, None] * mean[..., None, :]

    def _native_ready(self, *inputs: torch.Tensor) -> bool:
        """Whether :meth:`_native_moments` runs on these inputs
        (:func:`hgpdm_torch.native.usable`: float64 on the CPU, none of them and none of the GP's
        points and weights recording a gradient; Dx within the kernel's limit)."""
        weights = (self.inputs, self.kinv, self.beta, self.beta_rows, self.phi, self.term.weight)
        return self.dx <= native.MAX_D and native.usable(*inputs, *weights)

    def compiled(self) -> bool:
        """Whether :meth:`moments` runs on the compiled CPU kernel here (without gradients):
        float64 on a CPU where :mod:`hgpdm_torch.native` is available, Dx at most its limit."""
        return self._native_ready()

    @functools.cached_property
    def _native(self) -> _NativeLayout:
        U, L, dx = self.groups, self.group_size, self.dx
        n, up = U * L, -(-U // 8) * 8
        dev = self.kinv.device
        cols = torch.zeros(L, up, dtype=torch.long, device=dev)
        cols[:, :U] = (
            torch.arange(U, device=dev)[None, :] * L + torch.arange(L, device=dev)[:, None]
        )
        real = torch.zeros(L, up, dtype=torch.bool, device=dev)
        real[:, :U] = True
        cols, real = cols.reshape(-1), real.reshape(-1)
        beta = self.beta.reshape(n, dx).contiguous()
        kinv = self.kinv[:n, cols] * real
        betac = (beta[cols] * real[:, None]).T.contiguous()
        K = self.num_values
        phi_t = torch.nn.functional.pad(self.phi.T, (0, -(-K // 8) * 8 - K, 0, up - U))
        pairs = tuple(torch.triu_indices(dx, dx, device=cols.device))
        return _NativeLayout(cols, beta, betac, kinv.contiguous(), phi_t.contiguous(), up, pairs)

    def native_operands(
        self, mu: torch.Tensor, Sigma: torch.Tensor, log_phase: torch.Tensor | None = None
    ) -> tuple:
        """The arguments of :func:`hgpdm_torch.native.psi2_groups` for the inputs ``N(mu [B,
        Dx], Sigma [B, Dx, Dx])`` (and the log phase factors ``[B, UL]``): the points, the
        kernel's layout and each stream's quadratic forms
        (:func:`~hgpdm_torch.expectations.rbf_psi2_quadratic`,
        :func:`~hgpdm_torch.expectations.rbf_psi1_quadratic`, psi1's constant with the kernel's
        coefficient), computed by :func:`hgpdm_torch.native.rbf_forms`."""
        lay, b = self._native, mu.shape[0]
        Sigma = Sigma.expand(b, self.dx, self.dx).contiguous()
        weight = self.term.weight.contiguous()
        forms, consts, status = native.rbf_forms(Sigma, weight, float(self.coef))
        if bool(status.any()):  # not a covariance: torch's forms raise or add jitter, as before
            H, M_a, M_b, const = rbf_psi2_quadratic(self.term, self.term, Sigma)
            P, const1 = rbf_psi1_quadratic(self.term, Sigma)
            forms = torch.stack(torch.broadcast_tensors(H, M_a, M_b, P), -3).contiguous()
            consts = torch.stack(torch.broadcast_tensors(const, const1 + self.coef.log()), -1)
        phase = None if log_phase is None else log_phase.contiguous()
        return (
            self.inputs, lay.cols, mu.contiguous(), forms, consts.contiguous(), phase,
            lay.beta, lay.betac, lay.kinv, lay.phi_t, self.groups,
        )  # fmt: skip

    @functools.cached_property
    def native_moment_terms(self) -> torch.Tensor:
        """``[K U + K + 2 Dx + 1]``: what turns the kernel's contraction into the moments of
        :meth:`moments` (:func:`hgpdm_torch.native.predictive_step`'s ``trans``): phi ``[K,
        U]``, the process noise of each value ``[K]``, the output scales squared ``[Dx]`` (1
        where none), the offset ``[Dx]`` (0 where none) and the kernel's coefficient."""
        K, dx, ref = self.num_values, self.dx, self.phi
        parts = (
            self.phi.reshape(-1),
            self.noise.expand(K),
            ref.new_ones(dx) if self.scale2 is None else self.scale2,
            ref.new_zeros(dx) if self.offset is None else self.offset,
            self.coef.reshape(1),
        )
        return torch.cat([t.to(ref) for t in parts]).contiguous()  # a gradient: the torch step

    def log_phase(self, phase: torch.Tensor) -> torch.Tensor:
        """``[B, UL]`` the log of each point's phase factor ``-w_p (p - p_i)^2 / 2`` for the
        streams' phases ``[B]`` (a phase-aware GP only)."""
        return -0.5 * self.phase_weight * (phase[:, None] - self.phases).pow(2)

    def _native_moments(
        self, mu: torch.Tensor, Sigma: torch.Tensor, log_phase: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``psi1 [B, N]`` (times the phase factors), the traces ``[B, K]`` (:meth:`_trace`) and
        ``beta_k^T psi2 beta_k [B, K, Dx, Dx]`` by the compiled kernel
        (:func:`hgpdm_torch.native.psi2_groups`) in one call, from each stream's quadratic forms
        (:func:`~hgpdm_torch.expectations.rbf_psi2_quadratic`,
        :func:`~hgpdm_torch.expectations.rbf_psi1_quadratic`): the kernel builds the exponents'
        ``O(N Dx)`` factors itself, one stream at a time.

        The traces come from the kernel too (its ``out``'s last row), contracted as each row of
        ``T`` is complete.
        """
        b, K, (i, j) = mu.shape[0], self.num_values, self._native.pairs
        _, out, p1 = native.psi2_groups(*self.native_operands(mu, Sigma, log_phase))
        sums = out[:, :-1, :K].transpose(1, 2)  # [B, K, pairs]
        second = mu.new_empty(b, K, self.dx, self.dx)
        second[:, :, i, j] = sums
        second[:, :, j, i] = sums
        return p1.clone(), out[:, -1, :K].clone(), second

    def _tile(
        self,
        left: torch.Tensor,
        right: torch.Tensor,
        *,
        out: tuple[torch.Tensor, torch.Tensor] | None = None,
        bufs: tuple[torch.Tensor, ...] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``T [S, U, U]`` and ``beta_k^T psi2 beta_k [S, K, Dx, Dx]`` of one tile of S streams
        (:meth:`_fused_second`): into ``out`` with the ``bufs`` work space, or as new
        (differentiable) tensors."""
        s, dx, U, L = left.shape[0], self.dx, self.groups, self.group_size
        n, K = U * L, self.num_values
        if bufs is None:
            E = (left @ right).exp()
            P1 = self.beta_rows @ E.view(s, U, L, n)
            P2 = self.phi @ P1.view(s, U, dx * n)
            T = (E * self.kinv_cols).view(s, U, L * L, U).sum(2)
            return T, P2.view(s, K, dx, n) @ self.weighted_beta_cols
        E, P1, P2 = (buf[:s] for buf in bufs)
        exp_(torch.bmm(left, right, out=E))
        torch.matmul(self.beta_rows, E.view(s, U, L, n), out=P1)
        torch.matmul(self.phi, P1.view(s, U, dx * n), out=P2.view(s, K, dx * n))
        torch.matmul(P2, self.weighted_beta_cols, out=out[1])
        torch.sum(E.mul_(self.kinv_cols).view(s, U, L * L, U), 2, out=out[0])  # E is done
        return out

    def workspace(self) -> int:
        """Entries of the fused path's work space per stream: the tile ``N^2``, the group
        weights ``U Dx N`` and phi over groups ``K Dx N``."""
        n = self.groups * self.group_size
        return n * n + (self.groups + self.num_values) * self.dx * n

    def operations(self, streams: int = 1, *, cross: bool = True) -> OpCount:
        """Work of :meth:`moments` per stream on the fused path (the floor's count; nothing is
        shared between the ``streams`` of a call; ``cross`` as there).

        ``N^2`` exponentials and ``N`` for ``psi1``; multiply-adds: ``N^2 (Dx + 2)`` for the
        exponent, ``N^2 Dx`` for the group weights, ``K U^2`` for the traces, the ``O(N Dx^2)``
        and ``O(K U Dx)`` work of ``psi1``, the means and the centring, and with ``cross``,
        ``2 N Dx^2 + N Dx + K U Dx^2 + K Dx^3`` for ``E[grad k]`` and ``Cov[x, f]`` (with a
        phase, its ``N`` factors per stream and their products). Then, in
        torch, ``2 N^2`` for the product with ``K^-1`` and its group sums, ``K U Dx N`` for phi
        over groups and ``K Dx^2 N`` for the weighted columns; by the compiled kernel
        (:mod:`hgpdm_torch.native`, where it runs), ``N^2`` for the product with ``K^-1`` (one
        fused multiply-add), ``U P N`` for the weight pairs ``P = Dx (Dx + 1) / 2`` of each pair
        of groups and ``K U^2 P`` for phi over both groups.
        """
        dx, U, K = self.dx, self.groups, self.num_values
        n = U * self.group_size
        madds = n * n * (dx + 2) + n * n * dx + K * U * U + K * U + K * dx * dx
        madds += 2 * n * dx * dx + 2 * n * dx + K * U * dx
        if cross:
            madds += 2 * n * dx * dx + n * dx + K * U * dx * dx + K * dx**3
        if self.compiled():
            pairs = dx * (dx + 1) // 2
            madds += n * n + U * pairs * n + K * U * U * pairs + K * U * pairs
        else:
            madds += 2 * n * n + K * U * dx * n + K * dx * dx * n
        if self.phase:  # each point's phase factor, and its use in psi1, E[grad k], the exponent
            return OpCount(exps=n * n + 2 * n, madds=madds + n * (dx * cross + 5))
        return OpCount(exps=n * n + n, madds=madds)
