r"""A GP posterior evaluated at Gaussian inputs, in the form the VB free energy needs (thesis
App. 2.A).

Under ``x ~ N(mu, Sigma)`` the expected squared error of a GP mean ``m(x) = k(x, X) beta`` is

    E[||y - m(x)||^2] = ||y - psi1 beta||^2 + sum_d (beta_d^T psi2 beta_d - (psi1 beta_d)^2)
                        [+ tr Var[y] for a Gaussian target y = x_{t+1}],

with the kernel expectations ``psi1 = E[k(x, X)]`` and ``psi2 = E[k(X, x) k(x, X)]`` of
:mod:`hgpdm_torch.expectations` (App. 2.A's ``l`` and ``Q``, terms (a)-(d) of Eq. 16-17), and the
GP's predictive variance at a point (the plug-in ``sigma^2(mu_t)`` of Eq. 15-17).

Shapes: ``N`` training points, ``D`` input dim, ``Dout`` output dim; ``...`` leading batch dims.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from ...expectations import kernel_leaves, leaves_psi0, split_terms, term_k, term_psi1
from ...gp import GPPosterior, input_moments
from ...linalg import shared_matmul

__all__ = ["GaussianInputGP", "expected_sq_error"]


class GaussianInputGP:
    """A GP posterior in the form the free energy needs: all input columns Gaussian.

    ``X [..., N, D]``, ``beta [..., N, Dout]``, ``kinv [..., N, N]`` and a 0/1 ``mask [..., N]``
    (padding of per-code blocks), where ``...`` broadcasts against the inputs' batch dims;
    ``noise`` is the variance a new output adds: the GP's shared noise, or with a noise per code
    (``code_noise``) that of each input's code (a scalar for one code, ``[...]`` for several).

    With the codes of a block-diagonal (discrete g) kernel, code c reads only its own block.
    Codes that vary along a single batch axis (``[K, 1]``: the same K candidates for every
    window; ``[n, 1, 1]``: one code per row) are computed one code at a time, each on a view
    of its own unpadded block: padding every block to the largest one and copying it per entry
    would cost ``K max_c N_c^2`` instead of ``sum_c N_c^2`` per input Gaussian (3x on Weird
    Walking's unequal styles).
    """

    def __init__(self, post: GPPosterior, codes: torch.Tensor | None = None) -> None:
        self.post = post
        self.parts: list[GaussianInputGP] = []
        # the noise of a new output: the shared one (alpha_4), or with a noise per code
        # (HGPDM(noise_per_value=True)) that of the input's code, set per branch below
        self.noise = post.noise
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
            varying = [i for i, n in enumerate(codes.shape) if n > 1]
            if len(varying) == 1:
                axis = varying[0]
                self.axis = axis - codes.dim()  # from the right of the batch shape
                flat = codes.movedim(axis, -1).reshape(-1)
                self.groups = [torch.nonzero(flat == c).flatten() for c in torch.unique(flat)]
                self.order = torch.argsort(torch.cat(self.groups))
                self.parts = [
                    GaussianInputGP(post, codes.narrow(axis, int(i[0]), 1)) for i in self.groups
                ]
                return
            if codes.numel() == 1:  # one code: a view of its own block, without the padding
                c = int(codes.reshape(-1)[0])
                X, beta, kinv, mask = (b[c] for b in post.blocks())
                if post.code_noise is not None:
                    self.noise = post.code_noise[c]
                n = max(int(mask.sum()), 1)  # a code without training points keeps one pad row
                batch = codes.shape
                X, beta = X[:n].expand(*batch, n, -1), beta[:n].expand(*batch, n, -1)
                kinv = kinv[:n, :n].expand(*batch, n, n)
                mask = None if bool(mask[:n].all()) else mask[:n].expand(*batch, n)
            else:
                X, beta, kinv, mask = (b[codes] for b in post.blocks())
                if post.code_noise is not None:
                    self.noise = post.code_noise[codes.long()]  # [...], the batch shape
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
            if post.code_noise is not None:
                self.noise = post.code_noise[codes.long()]
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

    def _by_code(
        self,
        method: str,
        inputs: tuple[torch.Tensor, ...],
        events: tuple[int, ...],
        out_events: tuple[int, ...],
        **kwargs: object,
    ) -> tuple[torch.Tensor, ...]:
        """``method`` of each code's part on its entries of the inputs along the codes' batch
        axis, the outputs put back in order there. ``events`` / ``out_events``: the event dims
        of each input / output (a mean ``[..., D]`` has 1, a covariance or a Jacobian 2, a
        variance ``[...]`` 0)."""
        outs = []
        for idx, part in zip(self.groups, self.parts, strict=True):
            sliced = [
                x
                if x.dim() < e - self.axis or x.shape[self.axis - e] == 1  # broadcast there
                else x.index_select(self.axis - e, idx)
                for x, e in zip(inputs, events, strict=True)
            ]
            out = getattr(part, method)(*sliced, **kwargs)
            outs.append(out if isinstance(out, tuple) else (out,))
        return tuple(
            torch.cat(pieces, self.axis - e).index_select(self.axis - e, self.order)
            for e, pieces in zip(out_events, zip(*outs, strict=True), strict=True)
        )

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
        ``jacobian=True`` also returns ``d mean / d mu`` ``[..., Dout, D]`` and ``d var / d mu``
        ``[..., D]`` (``d k(mu, mu) - 2 (d k(mu, X)) K^-1 k(X, mu)``), from the kernel gradients of
        :func:`~hgpdm_torch.expectations.term_k`; these two are not differentiable.
        """
        if self.parts:
            events = (1, 0, 2, 1) if jacobian else (1, 0)
            return self._by_code("predict_point", (mu,), (1,), events, jacobian=jacobian)
        k, dk = 0.0, 0.0
        for t in self.terms:
            p, gr = term_k(t, mu, self.X, grad=jacobian)
            if jacobian:
                dk = dk + (gr if t.factor is None else t.factor[..., None, :] * gr)
            k = k + (p if t.factor is None else t.factor * p)
        # K^-1 k without copying a per-code K^-1 block for every input (it is symmetric)
        kinv_k = shared_matmul(self.kinv, k[..., :, None])[..., 0]
        quad = (kinv_k * k).sum(-1)
        kxx = leaves_psi0(self.leaves, mu, torch.zeros_like(mu).diag_embed(), None)
        mean = shared_matmul(self.beta.transpose(-1, -2), k[..., :, None])[..., 0]
        var = (kxx - quad).clamp_min(0.0) + self.noise
        if not jacobian:
            return mean, var
        # k(mu, mu) is constant for stationary parts; its linear parts' gradient by autograd on
        # the one formula of leaves_psi0
        with torch.enable_grad():
            at = mu.detach().requires_grad_(True)
            zero = torch.zeros_like(at).diag_embed()
            diag_k = leaves_psi0(self.leaves, at, zero, None).sum()
            dkxx = torch.autograd.grad(diag_k, at)[0] if diag_k.requires_grad else None
        dquad = 2.0 * (dk @ kinv_k[..., :, None])[..., 0]
        dvar = -dquad if dkxx is None else dkxx - dquad
        dvar = torch.where((kxx - quad)[..., None] > 0, dvar, torch.zeros_like(dvar))
        return mean, var, (dk @ self.beta).transpose(-1, -2), dvar.detach()

    def var_at_mean(self, mu: torch.Tensor) -> torch.Tensor:
        """Plug-in predictive variance at ``mu`` (Eq. 15 / 17), ``[...]``."""
        return self.predict_point(mu)[1]

    def mean_moments(
        self, mu: torch.Tensor, Sigma: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``E[m_d(x)]`` and ``E[m_d(x)^2]`` of the centred GP mean, each ``[..., Dout]``.

        ``E[m] = psi1 beta`` and ``E[m_d^2] = beta_d^T psi2 beta_d`` summed over kernel terms and
        term pairs (App. 2.A terms (a)-(d)), by :func:`~hgpdm_torch.gp.input_moments`.
        """
        if self.parts:
            return self._by_code("mean_moments", (mu, Sigma), (1, 2), (1, 1))
        mean, second, _, _ = input_moments(
            self.terms, mu, Sigma, self.X, self.beta, None, diagonal=True, grad=False
        )
        return mean, second


def expected_sq_error(
    y: torch.Tensor, y_var: torch.Tensor | None, mean: torch.Tensor, second: torch.Tensor
) -> torch.Tensor:
    """``E[(y_d - m_d)^2]`` per dim for independent ``y`` (mean y, variances y_var) and m."""
    err = y.pow(2) - 2.0 * y * mean + second
    return err if y_var is None else err + y_var
