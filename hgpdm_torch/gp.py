"""A GP conditioned on training data, shared by every inference routine.

:class:`GPPosterior` holds a zero-mean multi-output GP whose outputs share one kernel, conditioned
on training inputs ``X [N, Din]`` and targets ``Y [N, Dout]`` with white noise on the training
diagonal. It caches the Cholesky factor ``L`` of ``K + noise I`` and ``K^-1 Y``, and predicts at
points (Eq. 7 of the thesis, Sec. 3.2.1):

    mean(x) = k(x, X) K^-1 Y + offset,      var_d(x) = scale_d^2 (k(x, x) - k(x, X) K^-1 k(X, x)).

``scale`` and ``offset`` express the H-GPDM's measurement scaling: the GP models ``(z - offset) W``,
so predictions of z divide the variance by ``w_d^2`` and leave the mean unscaled.

At a Gaussian input ``x ~ N(mu, Sigma)`` :meth:`GPPosterior.predict_gaussian` matches the first
two moments of ``f(x)`` exactly (Sec. 3.3.1, Eq. 29-35; Deisenroth et al. 2012), from the kernel
expectations of :mod:`hgpdm_torch.expectations`.

Two more capabilities build on it (thesis Sec. 3.3.1-3.3.3):

- :meth:`GPPosterior.sparse` gives the deterministic training conditional (DTC) on M
  pseudo-inputs ``Z``, itself a ``GPPosterior`` whose ``weights`` and ``kinv`` live on ``Z``, so
  that :meth:`~GPPosterior.predict` and :meth:`~GPPosterior.predict_gaussian` work on it
  unchanged;
- :meth:`GPPosterior.shared_moments` gives the moments at one input Gaussian shared by K known
  values of the trailing input columns (an intention grid) for the IDDM's tensor-product kernel:
  :class:`~hgpdm_torch.gp_shared.SharedTransition`, with no ``N x N`` work per value.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import torch
from gpytorch.kernels import Kernel

from .expectations import Leaf, check_gaussian, kernel_leaves, leaves_psi0, split_terms
from .gp_shared import SharedTransition
from .kernels import DiscreteIntentionKernel
from .linalg import psd_cholesky, symmetrize
from .moments import input_moments
from .validation import as_tensor, check_shape

__all__ = ["GPPosterior", "input_moments"]


class GPPosterior:
    """Posterior of a zero-mean GP with a kernel shared by all output dimensions.

    Args:
        kernel: gpytorch kernel over ``[..., Din]`` inputs.
        train_inputs: ``[N, Din]`` training inputs.
        train_targets: ``[N, Dout]`` training targets (already centred; see ``offset``).
        noise: white-noise variance on the training diagonal: a positive scalar, or ``[N]``
            positive variances, one per training point (heteroscedastic noise, e.g. a process
            noise per value of a discrete intention).
        code_noise: optional ``[K]`` positive noise variance per code of a discrete intention
            (the last input column; needs a top-level ``DiscreteIntentionKernel``): the noise
            that ``include_noise=True`` adds at a test input of code k. Without it the noise
            added is the scalar ``noise`` (a per-point ``noise`` then refuses ``include_noise``).
        scale: ``[Dout]`` per-output standard-deviation scale of the predictive variance
            (``1 / w_d`` for the H-GPDM measurement GP); default ones.
        offset: ``[Dout]`` constant added to the predictive mean; default zeros.
        detach: whether to cut the autograd graph to the kernel hyperparameters and data (the
            default: a posterior of a fitted model is a constant for inference, and a cached
            graph would keep memory alive across filter steps).

    Attributes:
        chol: ``[N, N]`` lower Cholesky factor of ``K + noise I`` (``K + diag(noise)`` for a
            per-point noise).
        weights: ``[N, Dout]`` ``(K + noise I)^-1 Y``.
        kinv: ``[N, N]`` ``(K + noise I)^-1``.

    A sparse posterior (:meth:`sparse`) has the same interface with ``N`` replaced by the ``M``
    pseudo-inputs, which are its ``train_inputs``; it has no ``chol``.
    """

    def __init__(
        self,
        kernel: Kernel,
        train_inputs: torch.Tensor,
        train_targets: torch.Tensor,
        noise: float | torch.Tensor,
        *,
        code_noise: torch.Tensor | None = None,
        scale: torch.Tensor | None = None,
        offset: torch.Tensor | None = None,
        detach: bool = True,
    ) -> None:
        if not isinstance(kernel, Kernel):
            raise TypeError(f"kernel must be a gpytorch Kernel, got {type(kernel).__name__}")
        x = as_tensor(train_inputs, "train_inputs", ndim=2)
        y = as_tensor(train_targets, "train_targets", ndim=2, dtype=x.dtype, device=x.device)
        if x.shape[0] != y.shape[0] or x.shape[0] == 0:
            raise ValueError(
                f"train_inputs [N, Din] and train_targets [N, Dout] must have the same N > 0, got "
                f"{tuple(x.shape)} and {tuple(y.shape)}"
            )
        noise = torch.as_tensor(noise, dtype=x.dtype, device=x.device)
        if noise.shape not in ((), (x.shape[0],)) or not bool((noise > 0).all()):
            raise ValueError(
                f"noise must be a positive scalar or [N] = [{x.shape[0]}] positive variances, got "
                f"{noise if noise.dim() == 0 else tuple(noise.shape)}"
            )
        if code_noise is not None:
            code_noise = torch.as_tensor(code_noise, dtype=x.dtype, device=x.device)
            if not isinstance(kernel, DiscreteIntentionKernel) or kernel.active_dims is not None:
                raise ValueError(
                    "code_noise needs a discrete intention (a top-level DiscreteIntentionKernel), "
                    f"got a {type(kernel).__name__}"
                )
            if code_noise.shape != (kernel.num_values,) or not bool((code_noise > 0).all()):
                raise ValueError(
                    f"code_noise must be [K] = [{kernel.num_values}] positive variances, got "
                    f"{code_noise.tolist() if code_noise.dim() == 1 else code_noise}"
                )
        dout = y.shape[1]
        self.scale = self._vector(scale, "scale", dout, x, 1.0)
        self.offset = self._vector(offset, "offset", dout, x, 0.0)
        if detach:
            # A frozen snapshot: later changes to the model's kernel (e.g. more fitting) must not
            # leak into a posterior whose Cholesky factor was computed with the old values.
            kernel = copy.deepcopy(kernel)
            kernel.requires_grad_(False)
            x, y, noise = x.detach(), y.detach(), noise.detach()
            code_noise = None if code_noise is None else code_noise.detach()
            self.scale, self.offset = self.scale.detach(), self.offset.detach()
        self.kernel = kernel
        self.train_inputs, self.train_targets, self.noise = x, y, noise
        self.code_noise = code_noise
        self.detach = detach
        if detach:
            with torch.no_grad():
                self._factors = self._factorise()

    def _factorise(self) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.train_inputs
        k = self.kernel(x).to_dense()
        if self.noise.dim():  # one variance per training point
            k = k + torch.diag_embed(self.noise)
        else:
            k = k + self.noise * torch.eye(x.shape[0], dtype=x.dtype, device=x.device)
        chol = psd_cholesky(k, name="training kernel matrix K + noise I")
        return chol, torch.cholesky_solve(self.train_targets, chol)

    @property
    def chol(self) -> torch.Tensor:
        """``[N, N]`` lower Cholesky factor of ``K + noise I``.

        Cached for a detached posterior; recomputed on each access otherwise, so that every
        backward pass sees a fresh graph to the hyperparameters.
        """
        return self._factors[0] if self.detach else self._factorise()[0]

    @property
    def weights(self) -> torch.Tensor:
        """``[N, Dout]`` ``(K + noise I)^-1 Y`` (cached when detached, as :attr:`chol`)."""
        return self._factors[1] if self.detach else self._factorise()[1]

    @staticmethod
    def _vector(
        value: torch.Tensor | None, name: str, size: int, like: torch.Tensor, fill: float
    ) -> torch.Tensor:
        if value is None:
            return torch.full((size,), fill, dtype=like.dtype, device=like.device)
        v = as_tensor(value, name, ndim=1, dtype=like.dtype, device=like.device)
        if v.shape[0] != size:
            raise ValueError(f"{name} must have shape [{size}], got {tuple(v.shape)}")
        return v

    def to_dtype(self, dtype: torch.dtype) -> GPPosterior:
        """The same (detached) GP in another dtype, refactorised in it; ``self`` if it has it.

        Kernel, data, noises, scale and offset are cast; the Cholesky factor is recomputed in
        ``dtype`` (casting it would keep the rounding of the old dtype).
        """
        if self.train_inputs.dtype == dtype:
            return self
        return GPPosterior(
            copy.deepcopy(self.kernel).to(dtype),
            self.train_inputs.to(dtype),
            self.train_targets.to(dtype),
            self.noise.to(dtype),
            code_noise=None if self.code_noise is None else self.code_noise.to(dtype),
            scale=self.scale.to(dtype),
            offset=self.offset.to(dtype),
        )

    @property
    def input_dim(self) -> int:
        """``Din``, the number of input columns."""
        return self.train_inputs.shape[1]

    @property
    def output_dim(self) -> int:
        """``Dout``, the number of outputs."""
        return self.train_targets.shape[1]

    def _cross(self, x: torch.Tensor) -> torch.Tensor:
        """``k(x, X)`` for ``x [M, Din]`` -> ``[M, N]`` (differentiable in x)."""
        return self.kernel(x, self.train_inputs).to_dense()

    def predict(
        self, x: torch.Tensor, *, include_noise: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean and variance at points (Eq. 7).

        Args:
            x: ``[..., Din]`` test inputs (any leading batch dims).
            include_noise: add the training noise variance (scaled like the outputs), giving the
                predictive distribution of a new noisy observation instead of the latent function
                (with ``code_noise``: the noise of each input's code, its last column).

        Returns:
            ``mean [..., Dout]`` and ``var [..., Dout]`` (the outputs are independent given x),
            differentiable with respect to ``x`` (and, when not detached, the hyperparameters).
        """
        x = as_tensor(x, "x", min_ndim=1, dtype=self.train_inputs.dtype)
        check_shape(x, "x", [self.input_dim])
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.input_dim).to(self.train_inputs.device)
        kxX = self._cross(flat)
        mean = kxX @ self.weights + self.offset
        explained = self._explained_variance(kxX)
        kxx = self.kernel(flat, diag=True)
        f_var = (kxx - explained).clamp_min(0.0)
        if include_noise:
            f_var = f_var + self._test_noise(flat[:, -1])
        var = f_var.unsqueeze(-1) * self.scale.pow(2)
        return mean.reshape(*lead, self.output_dim), var.reshape(*lead, self.output_dim)

    def _explained_variance(self, kxX: torch.Tensor) -> torch.Tensor:
        """``diag(k(x, X) K^-1 k(X, x)) [P]`` for ``kxX [P, N]``, by a triangular solve."""
        v = torch.linalg.solve_triangular(self.chol, kxX.transpose(0, 1), upper=False)
        return v.pow(2).sum(0)

    @property
    def kinv(self) -> torch.Tensor:
        """``[N, N]`` ``(K + noise I)^-1`` from the Cholesky factor, computed once.

        Only the expected predictive variance uses it (``tr(K^-1 psi2)`` is an elementwise
        product with an ``N x N`` matrix, which a solve cannot do in ``O(N^2)``).
        """
        if not self.detach:
            return self._inverse()
        if getattr(self, "_kinv", None) is None:
            self._kinv = self._inverse()
        return self._kinv

    def _inverse(self) -> torch.Tensor:
        """:attr:`kinv`, uncached."""
        return torch.cholesky_inverse(self.chol)

    def _data(self) -> torch.Tensor:
        """``[N, Din]`` the inputs of the data the posterior is conditioned on."""
        return self.train_inputs

    def sparse(self, inducing_inputs: torch.Tensor) -> GPPosterior:
        r"""The sparse approximation of this GP on pseudo-inputs (DTC, thesis Sec. 3.3.3).

        The deterministic training conditional keeps the data ``X [N, Din], Y [N, Dout]`` and
        the kernel, and routes every prediction through the ``M`` pseudo-inputs ``Z``: with
        ``K_MM = k(Z, Z)``, ``K_MN = k(Z, X)`` and ``A = noise K_MM + K_MN K_NM`` ``[M, M]``::

            weights = A^-1 K_MN Y                         [M, Dout]
            kinv    = K_MM^-1 - noise A^-1                [M, M]
            mean(x) = k(x, Z) weights + offset
            var(x)  = scale^2 (k(x, x) - k(x, Z) K_MM^-1 k(Z, x) + noise k(x, Z) A^-1 k(Z, x))

        The result is a ``GPPosterior`` whose ``train_inputs`` are ``Z`` and whose ``weights``
        and ``kinv`` are the ones above, so :meth:`predict`, :meth:`predict_gaussian` (every
        option: known ``g``, batches of intentions, ``include_noise``, ``joint_cov``; a
        discrete intention's blocks, since ``K_MM`` and ``A`` are block-diagonal over codes too)
        and :meth:`shared_moments` work on it unchanged, at ``O(M^2)`` instead of ``O(N^2)``
        per input. With ``Z = X`` it is the exact GP where ``K_MM`` is well conditioned (else
        up to the ridge below: on fitted latents, variances within ~1%).

        ``kinv`` is a difference of two matrices as large as ``K_MM^-1``, so pseudo-inputs
        that nearly repeat each other would leave the moments to rounding noise: where the
        condition number of ``K_MM`` exceeds ``1e8`` (float64; ``1 / (10 eps)`` in a lower
        precision), ``K_MM`` gets the smallest ridge ``r I`` that brings it down to that (in
        ``A`` as well: a DTC whose inducing values carry noise ``r``); well-conditioned
        pseudo-inputs are left as they are. The ridge is held constant under autograd (with
        ``detach=False``, gradients are those of the GP with that ridge, not of the ridge's own
        dependence on the hyperparameters). Its :meth:`to_dtype` casts factors computed in its
        own dtype; :meth:`sparse` on it starts again from the data.

        Args:
            inducing_inputs: ``[M, Din]`` pseudo-inputs ``Z`` (finite; converted to the
                posterior's dtype and device).

        Returns:
            The sparse ``GPPosterior`` (detached iff this one is; not detached, its factors are
            recomputed on each access, so gradients reach the hyperparameters).

        Raises:
            ValueError: ``inducing_inputs`` not ``[M, Din]`` with ``M > 0`` or not finite; a
                noise per training point or per code (the DTC above assumes one noise).
        """
        x = self._data()
        z = as_tensor(inducing_inputs, "inducing_inputs", ndim=2, dtype=x.dtype, device=x.device)
        if z.shape[0] == 0 or z.shape[1] != self.input_dim:
            raise ValueError(
                f"inducing_inputs must be [M, Din] = [M > 0, {self.input_dim}], got "
                f"{tuple(z.shape)}"
            )
        if self.noise.dim() or self.code_noise is not None:
            per = "code (code_noise)" if self.code_noise is not None else "training point"
            raise ValueError(
                "the sparse DTC posterior on inducing inputs needs one noise shared by all "
                f"training points; this posterior has a noise per {per} (e.g. the transition GP "
                "of a model with noise_per_value=True): use the exact posterior (inducing=None)"
            )
        pieces = (self.kernel, x, self.train_targets, self.noise, self.scale, self.offset)
        return _DTCPosterior(*pieces, z.detach() if self.detach else z, detach=self.detach)

    def shared_moments(
        self, values: torch.Tensor, dtype: torch.dtype | None = None
    ) -> SharedTransition:
        r"""Moments of ``f(x, g_k) + noise`` at one input Gaussian over ``x`` for K known values
        ``g_k`` of the trailing input columns, organised for the IDDM's tensor-product kernel.

        The same moments as :meth:`predict_gaussian` at ``[x, g_k]`` with
        ``include_noise=True`` for every k, but ``psi2`` over ``x`` is computed once per input
        Gaussian and reduced over the groups of training points of equal ``g``:
        ``O(N^2 Dx + K U N Dx)`` instead of ``O(K N^2 Dx)`` (U distinct training values;
        :class:`~hgpdm_torch.gp_shared.SharedTransition`). On a :meth:`sparse` posterior the
        pseudo-inputs take the place of the training points.

        Args:
            values: ``[K, Dg]`` the grid of trailing-column values (intention values or codes),
                ``1 <= Dg < Din``.
            dtype: computation dtype (default the posterior's; weights and ``K^-1`` are cast).

        Returns:
            A :class:`~hgpdm_torch.gp_shared.SharedTransition`; its ``moments(mu [B, Dx],
            Sigma [B, Dx, Dx])`` gives ``mean [B, K, Dx]``, ``cov [B, K, Dx, Dx]`` and
            ``Cov[x, f] [B, K, Dx, Dx]``.

        Raises:
            TypeError: a kernel that is not one RBF over ``x`` times a factor of ``g``
                (:meth:`SharedTransition.supports
                <hgpdm_torch.gp_shared.SharedTransition.supports>`).
        """
        return SharedTransition(self, values, dtype)

    def predict_gaussian(
        self,
        mu: torch.Tensor,
        Sigma: torch.Tensor,
        *,
        g: torch.Tensor | None = None,
        include_noise: bool = False,
        joint_cov: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        r"""Exact mean and covariance of ``f(x~)`` at a Gaussian input (moment matching).

        The input is ``x~ = [x, g]``: ``x ~ N(mu, Sigma)`` covers the first ``D`` columns and the
        optional known ``g`` the remaining ``Din - D`` (a known continuous intention, or the code
        of a discrete one). A Gaussian intention correlated with ``x`` is simply part of ``x``.
        With ``beta = K^-1 Y`` and the kernel expectations ``psi0, psi1, psi2``
        (Eq. 29-31 and ``Q^x`` of Sec. 3.3.1)::

            mean = psi1 beta + offset
            cov  = beta^T psi2 beta - (psi1 beta)^T (psi1 beta)
                   + diag(scale^2 (psi0 - tr(K^-1 psi2) [+ noise]))
            Cov[x, f] = Sigma E[d k(x~, X)/dx] beta               (Stein's lemma)

        Cost (docs/design/speed.md#one-psi2-for-all-outputs). One shared ``N x N`` ``psi2`` serves
        all output pairs, and only RBF x RBF term pairs need one at all (pairs with a linear term
        have rank ``<= D``). Each kernel term splits into an ``x`` part and a per-training-point
        factor of ``g``, so the ``N x N`` work over ``x`` is done once for all ``g`` that share an
        input distribution: pass ``mu [B, 1, D]`` with ``g [B, K, Dg]`` (or ``g [K, 1, Dg]`` with
        ``mu [B, D]``) and each intention only rescales the training weights; temporaries are
        then ``O(B N^2 + B K N Dout)``. For a top-level ``DiscreteIntentionKernel`` each code
        touches only its own ``N_k`` training points (``O(B K N_k^2)``).

        With ``Sigma = 0`` this equals :meth:`predict`.

        Args:
            mu: ``[..., D]`` input mean.
            Sigma: ``[..., D, D]`` input covariance (symmetric PSD; may be singular).
            g: ``[..., Din - D]`` known trailing input columns, or ``None`` (``D = Din``).
            include_noise: add the training noise variance (scaled like the outputs) to the
                diagonal: the moments of a new noisy output (for the transition GP: the
                process noise ``alpha_4``; with ``code_noise``, that of the code ``g``, which
                must then be given).
            joint_cov: optional ``[..., S, D]`` covariance ``Cov[s, x]`` of another variable
                ``s`` jointly Gaussian with ``x``; the third output is then ``Cov[s, f]``.
                ``joint_cov = Sigma`` gives the default.

        Returns:
            ``mean [..., Dout]``, ``cov [..., Dout, Dout]`` and the input-output covariance
            ``Cov[x, f] [..., D, Dout]`` (``[..., S, Dout]`` with ``joint_cov``); ``...`` is the
            broadcast of the batch shapes of ``mu``, ``Sigma``, ``g``.
        """
        dtype, device = self.train_inputs.dtype, self.train_inputs.device
        mu, Sigma = check_gaussian(
            as_tensor(mu, "mu", min_ndim=1, dtype=dtype, device=device), Sigma
        )
        D, din = mu.shape[-1], self.input_dim
        if g is None:
            if D != din:
                raise ValueError(
                    f"mu must have {din} entries (the GP input dim) when g is None, got {D}"
                )
        else:
            g = as_tensor(g, "g", min_ndim=1, dtype=dtype, device=device)
            if D + g.shape[-1] != din:
                raise ValueError(
                    f"mu [..., {D}] and g [..., {g.shape[-1]}] must together have the GP input "
                    f"dim {din}"
                )
        if joint_cov is not None:
            joint_cov = as_tensor(joint_cov, "joint_cov", min_ndim=2, dtype=dtype, device=device)
            check_shape(joint_cov, "joint_cov", [None, D])

        leaves = self._leaves()
        if g is not None and self.blocks() is not None:
            # discrete g: each code touches only its own training points
            # (docs/design/speed.md#a-discrete-intentions-own-block)
            X, beta, kinv, mask = self._gather_blocks(g)
            leaves = [replace(lf, weight=lf.weight[:D], codes=()) for lf in leaves]
            terms = [replace(t, factor=mask) for t in split_terms(leaves, X, None, D)]
            g_psi0 = None
        else:
            X, beta, kinv = self.train_inputs, self.weights, self.kinv
            terms = split_terms(leaves, X, g, D)
            g_psi0 = g
        mean, second, trace, grad = input_moments(terms, mu, Sigma, X[..., :D], beta, kinv)
        var = (leaves_psi0(leaves, mu, Sigma, g_psi0) - trace).clamp_min(0.0)
        if include_noise:
            if self.code_noise is not None and g is None:
                raise ValueError(
                    "include_noise with a noise per code (code_noise) needs the code g of the input"
                )
            var = var + self._test_noise(None if g is None else g[..., -1])
        # beta^T psi2 beta and mean mean^T nearly cancel when the GP is almost exact (small
        # noise), so their difference is projected onto the PSD cone where rounding broke it.
        diag = torch.diag_embed(var[..., None] * self.scale.pow(2))
        cov = _psd_part(symmetrize(second - mean[..., :, None] * mean[..., None, :]), diag)
        io = (Sigma if joint_cov is None else joint_cov) @ grad
        return mean + self.offset, cov, io

    def _test_noise(self, code: torch.Tensor | None) -> torch.Tensor:
        """Noise variance of a new output at inputs of discrete code ``code [...]`` (any shape;
        only used with ``code_noise``): ``code_noise[code]``, or the scalar ``noise``."""
        if self.code_noise is not None:
            c = code.round()
            num = len(self.code_noise)
            if bool((c != code).any()) or bool(((c < 0) | (c >= num)).any()):
                raise ValueError(f"discrete intention codes g must be integers in [0, {num - 1}]")
            return self.code_noise[c.long()]
        if self.noise.dim():
            raise ValueError(
                "include_noise needs a scalar noise or a noise per code (code_noise); this "
                "posterior has only a noise per training point"
            )
        return self.noise

    def _leaves(self) -> list[Leaf]:
        """Kernel leaves; cached when detached (the posterior is then a frozen snapshot)."""
        if self.detach and getattr(self, "_leaf_cache", None) is not None:
            return self._leaf_cache
        leaves = kernel_leaves(self.kernel, self.input_dim)
        if self.detach:
            self._leaf_cache = leaves
        return leaves

    def blocks(self) -> tuple[torch.Tensor, ...] | None:
        """Per-code padded training blocks of a top-level ``DiscreteIntentionKernel``, or None.

        ``(X [K, M, Din], beta [K, M, Dout], kinv [K, M, M], mask [K, M])`` with ``M`` the largest
        block. ``K + noise I`` is block-diagonal over codes, so its inverse's block for code c is
        ``(K_cc + noise I)^-1`` and ``beta``'s rows of code c are that block's weights.
        """
        kernel = self.kernel
        if not isinstance(kernel, DiscreteIntentionKernel) or kernel.active_dims is not None:
            return None
        if not self.detach or getattr(self, "_block_cache", None) is None:
            codes = self.train_inputs[:, -1]
            index = [torch.nonzero(codes == c).flatten() for c in range(kernel.num_values)]
            M = max(1, max(len(i) for i in index))
            kinv = self.kinv
            n, dout = len(codes), self.output_dim
            pad = torch.full((kernel.num_values, M), n, dtype=torch.long, device=codes.device)
            for c, i in enumerate(index):
                pad[c, : len(i)] = i
            mask = (pad < n).to(kinv.dtype)
            X = torch.cat([self.train_inputs, self.train_inputs.new_zeros(1, self.input_dim)])
            beta = torch.cat([self.weights, self.weights.new_zeros(1, dout)])
            kinv = torch.nn.functional.pad(kinv, (0, 1, 0, 1))
            blocks = (X[pad], beta[pad], kinv[pad[:, :, None], pad[:, None, :]], mask)
            if not self.detach:
                return blocks
            self._block_cache = blocks
        return self._block_cache

    def _gather_blocks(self, g: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The blocks of the codes ``g [..., 1]``: X, beta, kinv, mask with batch ``[...]``."""
        if g.shape[-1] != 1:
            raise ValueError(
                f"a discrete intention g must have one column (the code), got {g.shape}"
            )
        code = g[..., 0].round()
        num = self.kernel.num_values
        if bool((code != g[..., 0]).any()) or bool(((code < 0) | (code >= num)).any()):
            raise ValueError(f"discrete intention codes g must be integers in [0, {num - 1}]")
        code = code.long()
        return tuple(block[code] for block in self.blocks())


def _psd_part(a: torch.Tensor, diag: torch.Tensor) -> torch.Tensor:
    """``a + diag`` with ``a [..., n, n]`` clipped to PSD (eigenvalues >= 0) where needed.

    A batched Cholesky of ``a + diag`` finds the members that need it; only those pay for an
    eigendecomposition, so the common case costs one small Cholesky per batch member.
    """
    total = a + diag
    with torch.no_grad():
        _, info = torch.linalg.cholesky_ex(total)
        bad = info > 0
    if not bool(bad.any()):
        return total
    w, v = torch.linalg.eigh(a[bad])
    fixed = (v * w.clamp_min(0.0)[..., None, :]) @ v.transpose(-1, -2)
    out = total.clone()
    out[bad] = symmetrize(fixed) + diag.expand_as(total)[bad]
    return out


# Smallest ratio of the smallest to the largest eigenvalue of K_MM that GPPosterior.sparse lets
# through (float64; ten machine epsilons in a lower precision); below it, the smallest ridge that
# restores it is added to K_MM. The DTC's kinv = K_MM^-1 - noise A^-1 cancels two matrices as
# large as K_MM^-1, and pseudo-inputs that nearly repeat each other (neighbouring latents on nearby
# intention values) make K_MM singular to rounding (condition numbers 1e15-1e18 on fitted IDDMs,
# where the covariances came out as rounding noise at the 1e-2 level, two summation orders
# disagreeing by that much). At 1e8 they agree to 1e-9 and are closer to the exact GP's.
_MIN_EIGEN_RATIO = 1e-8


class _DTCPosterior(GPPosterior):
    """:meth:`GPPosterior.sparse`: the DTC approximation, a posterior on the pseudo-inputs.

    ``train_inputs`` are the pseudo-inputs ``Z [M, Din]``; ``data_inputs [N, Din]`` and
    ``train_targets [N, Dout]`` the data it is conditioned on. The factors are
    ``(L_MM, weights, L_A)``: the Cholesky factors of ``K_MM`` (with its ridge, if any) and
    ``A = noise K_MM + K_MN K_NM``, and ``A^-1 K_MN Y``.
    """

    def __init__(
        self,
        kernel: Kernel,
        data_inputs: torch.Tensor,
        train_targets: torch.Tensor,
        noise: torch.Tensor,
        scale: torch.Tensor,
        offset: torch.Tensor,
        inducing_inputs: torch.Tensor,
        *,
        detach: bool,
    ) -> None:
        # no GPPosterior.__init__: the pieces come checked (and detached) from a posterior
        self.kernel, self.detach, self.noise, self.code_noise = kernel, detach, noise, None
        self.data_inputs, self.train_targets = data_inputs, train_targets
        self.train_inputs, self.scale, self.offset = inducing_inputs, scale, offset
        if detach:
            with torch.no_grad():
                self._factors = self._factorise()

    def _factorise(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        z, x = self.train_inputs, self.data_inputs
        kmm = self.kernel(z).to_dense()
        with torch.no_grad():  # a numerical safeguard, not part of the model: no gradient
            lam = torch.linalg.eigvalsh(kmm)  # ascending
            floor = max(_MIN_EIGEN_RATIO, 10 * torch.finfo(kmm.dtype).eps)
            ridge = (floor * lam[-1] - lam[0]).clamp_min(0.0)
        kmm = kmm + ridge * torch.eye(len(z), dtype=kmm.dtype, device=kmm.device)
        kmn = self.kernel(z, x).to_dense()
        chol_m = psd_cholesky(kmm, name="inducing kernel matrix K_MM")
        a = self.noise * kmm + kmn @ kmn.transpose(0, 1)
        chol_a = psd_cholesky(a, name="DTC matrix noise K_MM + K_MN K_NM")
        return chol_m, torch.cholesky_solve(kmn @ self.train_targets, chol_a), chol_a

    def _current(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self._factors if self.detach else self._factorise()

    @property
    def chol(self) -> torch.Tensor:
        raise AttributeError(
            "a sparse (DTC) posterior has no Cholesky factor of K + noise I: use its weights and "
            "kinv (K_MM^-1 - noise A^-1)"
        )

    @property
    def weights(self) -> torch.Tensor:
        """``[M, Dout]`` ``A^-1 K_MN Y``."""
        return self._current()[1]

    def _explained_variance(self, kxX: torch.Tensor) -> torch.Tensor:
        # k K_MM^-1 k^T - noise k A^-1 k^T by two solves: better conditioned than through kinv
        chol_m, _, chol_a = self._current()
        kt = kxX.transpose(0, 1)
        vm = torch.linalg.solve_triangular(chol_m, kt, upper=False)
        va = torch.linalg.solve_triangular(chol_a, kt, upper=False)
        return vm.pow(2).sum(0) - self.noise * va.pow(2).sum(0)

    def _inverse(self) -> torch.Tensor:
        chol_m, _, chol_a = self._current()
        inverse = torch.cholesky_inverse(chol_m) - self.noise * torch.cholesky_inverse(chol_a)
        return symmetrize(inverse)

    def _data(self) -> torch.Tensor:
        return self.data_inputs

    def to_dtype(self, dtype: torch.dtype) -> GPPosterior:
        """The same (detached) sparse GP in another dtype: factors and ``kinv`` computed in this
        one's dtype, then cast.

        Unlike the exact GP's, they are not recomputed in ``dtype``: ``kinv = K_MM^-1 - noise
        A^-1`` cancels two matrices as large as ``K_MM^-1`` (``A`` has condition numbers of
        1e12-1e14 on fitted models), which float32 would leave to rounding.
        """
        if self.train_inputs.dtype == dtype:
            return self
        low = copy.copy(self)
        low.kernel = copy.deepcopy(self.kernel).to(dtype).requires_grad_(False)
        for name in ("data_inputs", "train_targets", "noise", "scale", "offset", "train_inputs"):
            setattr(low, name, getattr(self, name).detach().to(dtype))
        low.detach = True
        with torch.no_grad():
            low._factors = tuple(f.to(dtype) for f in self._current())
            low._kinv = self.kinv.detach().to(dtype)
        return low
