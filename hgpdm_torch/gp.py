"""A GP conditioned on training data, shared by every inference routine.

:class:`GPPosterior` holds a zero-mean multi-output GP whose outputs share one kernel, conditioned
on training inputs ``X [N, Din]`` and targets ``Y [N, Dout]`` with white noise on the training
diagonal. It caches the Cholesky factor ``L`` of ``K + noise I`` and ``K^-1 Y``, and predicts at
points (Eq. 7 of the thesis, Sec. 3.2.1):

    mean(x) = k(x, X) K^-1 Y + offset,      var_d(x) = scale_d^2 (k(x, x) - k(x, X) K^-1 k(X, x)).

``scale`` and ``offset`` express the H-GPDM's measurement scaling: the GP models ``(z - offset) W``,
so predictions of z divide the variance by ``w_d^2`` and leave the mean unscaled.
"""

from __future__ import annotations

import torch
from gpytorch.kernels import Kernel

from .linalg import psd_cholesky
from .validation import as_tensor, check_shape

__all__ = ["GPPosterior"]


class GPPosterior:
    """Posterior of a zero-mean GP with a kernel shared by all output dimensions.

    Args:
        kernel: gpytorch kernel over ``[..., Din]`` inputs.
        train_inputs: ``[N, Din]`` training inputs.
        train_targets: ``[N, Dout]`` training targets (already centred; see ``offset``).
        noise: white-noise variance on the training diagonal (scalar, > 0).
        scale: ``[Dout]`` per-output standard-deviation scale of the predictive variance
            (``1 / w_d`` for the H-GPDM measurement GP); default ones.
        offset: ``[Dout]`` constant added to the predictive mean; default zeros.
        detach: whether to cut the autograd graph to the kernel hyperparameters and data (the
            default: a posterior of a fitted model is a constant for inference, and a cached
            graph would keep memory alive across filter steps).

    Attributes:
        chol: ``[N, N]`` lower Cholesky factor of ``K + noise I``.
        weights: ``[N, Dout]`` ``(K + noise I)^-1 Y``.
    """

    def __init__(
        self,
        kernel: Kernel,
        train_inputs: torch.Tensor,
        train_targets: torch.Tensor,
        noise: float | torch.Tensor,
        *,
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
        if noise.dim() != 0 or not bool(noise > 0):
            raise ValueError(f"noise must be a positive scalar, got {noise}")
        dout = y.shape[1]
        self.scale = self._vector(scale, "scale", dout, x, 1.0)
        self.offset = self._vector(offset, "offset", dout, x, 0.0)
        self.kernel = kernel
        with torch.set_grad_enabled(torch.is_grad_enabled() and not detach):
            k = kernel(x).to_dense()
            eye = torch.eye(x.shape[0], dtype=x.dtype, device=x.device)
            self.chol = psd_cholesky(k + noise * eye, name="training kernel matrix K + noise I")
            self.weights = torch.cholesky_solve(y, self.chol)
        if detach:
            x, y, noise = x.detach(), y.detach(), noise.detach()
            self.scale, self.offset = self.scale.detach(), self.offset.detach()
        self.train_inputs, self.train_targets, self.noise = x, y, noise
        self.detach = detach

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

    @property
    def input_dim(self) -> int:
        """``Din``, the number of input columns."""
        return self.train_inputs.shape[1]

    @property
    def output_dim(self) -> int:
        """``Dout``, the number of outputs."""
        return self.train_targets.shape[1]

    def _cross(self, x: torch.Tensor) -> torch.Tensor:
        """``k(x, X)`` for ``x [M, Din]`` -> ``[M, N]``."""
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.detach):
            return self.kernel(x, self.train_inputs).to_dense()

    def predict(
        self, x: torch.Tensor, *, include_noise: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Predictive mean and variance at points (Eq. 7).

        Args:
            x: ``[..., Din]`` test inputs (any leading batch dims).
            include_noise: add the training noise variance (scaled like the outputs), giving the
                predictive distribution of a new noisy observation instead of the latent function.

        Returns:
            ``mean [..., Dout]`` and ``var [..., Dout]`` (the outputs are independent given x).
        """
        x = as_tensor(x, "x", min_ndim=1, dtype=self.train_inputs.dtype)
        check_shape(x, "x", [self.input_dim])
        lead = x.shape[:-1]
        flat = x.reshape(-1, self.input_dim).to(self.train_inputs.device)
        kxX = self._cross(flat)
        mean = kxX @ self.weights + self.offset
        v = torch.linalg.solve_triangular(self.chol, kxX.transpose(0, 1), upper=False)
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.detach):
            kxx = self.kernel(flat, diag=True)
        f_var = (kxx - v.pow(2).sum(0)).clamp_min(0.0)
        if include_noise:
            f_var = f_var + self.noise
        var = f_var.unsqueeze(-1) * self.scale.pow(2)
        return mean.reshape(*lead, self.output_dim), var.reshape(*lead, self.output_dim)
