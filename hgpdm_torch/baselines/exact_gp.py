"""The exact GP of the GP baselines: constant mean, ARD RBF kernel, marginal-likelihood fit.

Shared by :class:`~hgpdm_torch.baselines.regression.WindowGPR` (one GP on a continuous target)
and :class:`~hgpdm_torch.baselines.classification.WindowGPC` (a batch of one GP per class on
Dirichlet-transformed labels).
"""

from __future__ import annotations

import gpytorch
import torch

__all__: list[str] = []


class ExactGPModel(gpytorch.models.ExactGP):
    def __init__(
        self, x: torch.Tensor, y: torch.Tensor, likelihood, batch_shape: torch.Size | None = None
    ):
        super().__init__(x, y, likelihood)
        batch_shape = batch_shape or torch.Size()
        self.mean_module = gpytorch.means.ConstantMean(batch_shape=batch_shape)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(ard_num_dims=x.shape[-1], batch_shape=batch_shape),
            batch_shape=batch_shape,
        )

    def forward(self, x: torch.Tensor) -> gpytorch.distributions.MultivariateNormal:
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def fit_marginal_likelihood(model, likelihood, x, y, steps: int, lr: float) -> None:
    """Maximise the exact marginal likelihood with Adam (the standard gpytorch routine)."""
    model.train()
    likelihood.train()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
    for _ in range(steps):
        opt.zero_grad()
        loss = -mll(model(x), y).sum()
        loss.backward()
        opt.step()
    model.eval()
    likelihood.eval()
