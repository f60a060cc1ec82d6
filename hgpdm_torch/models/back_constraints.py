"""Back-constrained latent states: ``X = f(Z)`` instead of free parameters.

In a GPDM the latent states are free, so nearby observations can end up far apart in latent space
and a new sequence has no direct latent position. Back-constraints (Lawrence & Quinonero-Candela,
ICML 2006) make the latent states a smooth function of the observations, ``x_n = f(z_n)``, and
optimise the parameters of f instead of X. Similar poses then get similar latent positions, and
``f`` places new frames in the same latent space as the training frames.

Two maps are provided; any ``torch.nn.Module`` taking ``[..., Dz]`` to ``[..., Dx]`` with an
``initialise(inputs, latent)`` method can be passed to the models instead:

- :class:`KernelBackConstraint`: ``f(z) = sum_m a_m k(z, z_m)`` with a fixed RBF kernel over the
  training frames (gpytorch ``RBFKernel``) and learned weights ``A [M, Dx]``;
- :class:`MLPBackConstraint`: a one-hidden-layer tanh network.

Both start at (a least-squares fit of) the model's initial latents, so a back-constrained model
starts where the free model would.
"""

from __future__ import annotations

import torch
from gpytorch.kernels import RBFKernel

from ..linalg import psd_cholesky

__all__ = ["BACK_CONSTRAINTS", "KernelBackConstraint", "MLPBackConstraint", "make_back_constraint"]

BACK_CONSTRAINTS = ("kernel", "mlp")


class KernelBackConstraint(torch.nn.Module):
    """``f(z) = K(z, Z) A``: an RBF kernel expansion over the ``M`` training frames ``Z``.

    Args:
        inputs: ``[M, Dz]`` training frames (standardised), the kernel centres.
        latent_dim: ``Dx``.
        lengthscale: RBF length scale in input units (default: the median distance between
            training frames, a common heuristic); fixed, not learned.
        ridge: regularisation of the least-squares start ``A = (K + ridge I)^-1 X0``.

    Attributes:
        weights: ``[M, Dx]`` parameter ``A``.
    """

    def __init__(
        self,
        inputs: torch.Tensor,
        latent_dim: int,
        *,
        lengthscale: float | None = None,
        ridge: float = 1e-6,
    ) -> None:
        super().__init__()
        if inputs.dim() != 2:
            raise ValueError(f"inputs must be [M, Dz], got {tuple(inputs.shape)}")
        if not ridge > 0:
            raise ValueError(f"ridge must be positive, got {ridge!r}")
        self.register_buffer("centres", inputs.detach().clone())
        if lengthscale is None:
            d = torch.cdist(inputs, inputs)
            lengthscale = float(d[d > 0].median()) if bool((d > 0).any()) else 1.0
        if not lengthscale > 0:
            raise ValueError(f"lengthscale must be positive, got {lengthscale!r}")
        self.kernel = RBFKernel().to(inputs.dtype)
        self.kernel.lengthscale = lengthscale
        self.kernel.raw_lengthscale.requires_grad_(False)
        self.ridge = float(ridge)
        self.weights = torch.nn.Parameter(inputs.new_zeros(inputs.shape[0], latent_dim))

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """``[..., Dz] -> [..., Dx]``."""
        k = self.kernel(z, self.centres).to_dense()
        return k @ self.weights

    @torch.no_grad()
    def initialise(self, inputs: torch.Tensor, latent: torch.Tensor) -> None:
        """Least-squares weights so that ``f(inputs) ~= latent`` (``[M, Dz]``, ``[M, Dx]``)."""
        k = self.kernel(inputs, self.centres).to_dense()
        gram = k.T @ k + self.ridge * torch.eye(k.shape[1], dtype=k.dtype, device=k.device)
        self.weights.copy_(torch.cholesky_solve(k.T @ latent, psd_cholesky(gram, name="K^T K")))


class MLPBackConstraint(torch.nn.Module):
    """``f(z) = W_2 tanh(W_1 z + b_1) + b_2`` with ``hidden`` units.

    Args:
        obs_dim: ``Dz``; latent_dim: ``Dx``; hidden: hidden units; seed: initial weights.
    """

    def __init__(self, obs_dim: int, latent_dim: int, *, hidden: int = 32, seed: int = 0) -> None:
        super().__init__()
        if hidden < 1:
            raise ValueError(f"hidden must be a positive int, got {hidden!r}")
        gen = torch.Generator().manual_seed(seed)
        self.hidden = torch.nn.Linear(obs_dim, hidden)
        self.out = torch.nn.Linear(hidden, latent_dim)
        with torch.no_grad():
            for layer in (self.hidden, self.out):
                bound = layer.in_features**-0.5
                layer.weight.copy_((torch.rand(layer.weight.shape, generator=gen) * 2 - 1) * bound)
                layer.bias.zero_()

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """``[..., Dz] -> [..., Dx]``."""
        return self.out(torch.tanh(self.hidden(z)))

    def initialise(self, inputs: torch.Tensor, latent: torch.Tensor, steps: int = 200) -> None:
        """Fit the network to ``latent`` by L-BFGS on the squared error (a regression start)."""
        opt = torch.optim.LBFGS(
            self.parameters(), max_iter=steps, line_search_fn="strong_wolfe", tolerance_change=0
        )

        def closure() -> torch.Tensor:
            opt.zero_grad()
            loss = (self(inputs) - latent).pow(2).mean()
            loss.backward()
            return loss

        with torch.enable_grad():
            opt.step(closure)
        for p in self.parameters():
            p.grad = None


def make_back_constraint(
    kind: str | torch.nn.Module, inputs: torch.Tensor, latent: torch.Tensor
) -> torch.nn.Module:
    """Build (``"kernel"``, ``"mlp"``) or take a user module, and start it at ``latent``.

    Args:
        kind: a name of :data:`BACK_CONSTRAINTS` or a module with ``initialise(inputs, latent)``.
        inputs: ``[M, Dz]`` standardised training frames; latent: ``[M, Dx]`` initial latents.
    """
    if isinstance(kind, str):
        if kind not in BACK_CONSTRAINTS:
            raise ValueError(f"back_constraint must be one of {BACK_CONSTRAINTS}, got {kind!r}")
        dx = latent.shape[-1]
        module: torch.nn.Module = (
            KernelBackConstraint(inputs, dx)
            if kind == "kernel"
            else MLPBackConstraint(inputs.shape[-1], dx).to(inputs.dtype)
        )
    elif isinstance(kind, torch.nn.Module) and hasattr(kind, "initialise"):
        module = kind.to(inputs.dtype)
    else:
        raise TypeError(
            "back_constraint must be 'kernel', 'mlp' or a torch module with an "
            f"initialise(inputs, latent) method, got {kind!r}"
        )
    module.initialise(inputs, latent)
    return module
