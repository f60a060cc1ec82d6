r"""The variational family of VB inference as a Pyro guide (thesis Eq. 11, Sec. 2.3.3).

The mean-field family over the latent states of a window (and a continuous g):

    q(x_{1:T}) = prod_t N(x_t | mu_t, Sigma_t),     Sigma_t = L_t L_t^T,
    q(g) = N(g | mu_g, Sigma_g)                      (Sec. 2.3.3, continuous g only),

with entropy ``H(q) = sum_t 1/2 log|2 pi e Sigma_t| [+ 1/2 log|2 pi e Sigma_g|]``, the last term
of the negative free energy of Eq. 13.

Shapes: ``T`` window length, ``Dx`` latent dim, ``Dg`` dim of a continuous g; ``...`` leading
batch dims (windows ``B``, candidates of g ``K``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import pyro
import pyro.distributions as dist
import torch
from pyro.distributions import constraints
from pyro.nn import PyroModule, PyroParam

from ...gaussian import entropy
from ...linalg import psd_cholesky, symmetrize
from ...validation import as_tensor

__all__ = ["MeanFieldGuide", "batch_plates"]


@contextmanager
def batch_plates(shape: torch.Size, device: torch.device) -> Iterator[None]:
    """One :class:`pyro.plate` per batch dim of ``shape`` (windows and candidates of g are
    independent problems), as ``pyro.plate_stack`` but with the plates' indices on ``device``."""
    with ExitStack() as stack:
        for i, size in enumerate(shape):
            plate = pyro.plate(f"vb_batch_{i}", size, dim=i - len(shape), device=device)
            stack.enter_context(plate)
        yield


class MeanFieldGuide(PyroModule):
    r"""Mean-field Gaussian guide ``q(x_{1:T}) [q(g)]`` (Eq. 11; Sec. 2.3.3).

    Parameters are :class:`pyro.nn.PyroParam` s: ``loc [..., T, Dx]`` and ``scale_tril
    [..., T, Dx, Dx]`` under ``constraints.lower_cholesky`` (so every ``Sigma_t = L_t L_t^T`` is
    positive definite), and optionally ``g_loc [..., Dg]``, ``g_scale_tril [..., Dg, Dg]``.

    Calling the guide samples the sites ``"x"`` (event shape ``[T, Dx]``) and ``"g"``, so it can be
    used with ``pyro.infer`` (e.g. ``Trace_ELBO`` against
    :func:`~hgpdm_torch.inference.variational.svi.pyro_model`, or ``SVI`` with the closed-form
    loss of :func:`~hgpdm_torch.inference.variational.svi.closed_form_loss`);
    :meth:`~hgpdm_torch.inference.variational.window.WindowModel.free_energy` evaluates the same
    objective in closed form. Pyro keeps parameters in one global store by name, so use a new
    guide in a fresh store (``pyro.clear_param_store()`` or ``pyro.get_param_store().scope()``):
    guides share parameter names.

    Args:
        loc: ``[..., T, Dx]`` initial means.
        cov: ``[..., T, Dx, Dx]`` initial covariances.
        g_loc: ``[..., Dg]`` initial mean of a continuous g, or ``None``.
        g_cov: ``[..., Dg, Dg]`` its initial covariance.
    """

    def __init__(
        self,
        loc: torch.Tensor,
        cov: torch.Tensor,
        g_loc: torch.Tensor | None = None,
        g_cov: torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        loc = as_tensor(loc, "loc", min_ndim=2)
        cov = as_tensor(cov, "cov", min_ndim=3, dtype=loc.dtype, device=loc.device)
        if cov.shape != (*loc.shape, loc.shape[-1]):
            raise ValueError(
                f"cov must have shape {(*loc.shape, loc.shape[-1])} to match loc, "
                f"got {tuple(cov.shape)}"
            )
        self.loc = PyroParam(loc.detach().clone())
        self.scale_tril = PyroParam(
            psd_cholesky(symmetrize(cov.detach()), name="initial covariance of q(x)"),
            constraint=constraints.lower_cholesky,
        )
        self.has_g = g_loc is not None
        if self.has_g:
            g_loc = as_tensor(g_loc, "g_loc", min_ndim=1, dtype=loc.dtype, device=loc.device)
            if g_cov is None:
                raise ValueError("g_cov is required with g_loc")
            g_cov = as_tensor(g_cov, "g_cov", min_ndim=2, dtype=loc.dtype, device=loc.device)
            self.g_loc = PyroParam(g_loc.detach().clone())
            self.g_scale_tril = PyroParam(
                psd_cholesky(symmetrize(g_cov.detach()), name="initial covariance of q(g)"),
                constraint=constraints.lower_cholesky,
            )

    @property
    def cov(self) -> torch.Tensor:
        """``[..., T, Dx, Dx]`` covariances ``Sigma_t``."""
        L = self.scale_tril
        return L @ L.transpose(-1, -2)

    @property
    def g_cov(self) -> torch.Tensor:
        """``[..., Dg, Dg]`` covariance of q(g)."""
        L = self.g_scale_tril
        return L @ L.transpose(-1, -2)

    def q(self) -> tuple[torch.Tensor | None, ...]:
        """``(loc, scale_tril, g_loc, g_scale_tril)`` (``None`` for q(g) without a continuous g).

        Read outside Pyro's context: this does not touch Pyro's parameter store (see
        :func:`~hgpdm_torch.inference.variational.svi.closed_form_loss` for the read that does).
        """
        g = (self.g_loc, self.g_scale_tril) if self.has_g else (None, None)
        return self.loc, self.scale_tril, *g

    def entropy(self) -> torch.Tensor:
        """``H(q)`` ``[...]``: ``sum_t 1/2 log|2 pi e Sigma_t|`` (+ the entropy of q(g))."""
        h = entropy(self.scale_tril).sum(-1)
        return h + entropy(self.g_scale_tril) if self.has_g else h

    def forward(self, *args: object, **kwargs: object) -> torch.Tensor | tuple[torch.Tensor, ...]:
        """Sample ``x [..., T, Dx]`` (site ``"x"``) and, with a continuous g, ``g [..., 1, Dg]``.

        The arguments of the model (``pyro.infer`` passes them to the guide too) are ignored.
        """
        loc, tril = self.loc, self.scale_tril
        with batch_plates(loc.shape[:-2], loc.device):
            x = pyro.sample("x", dist.MultivariateNormal(loc, scale_tril=tril).to_event(1))
            if not self.has_g:
                return x
            # batch [..., 1]: g aligned with the candidate axis K (= 1) of "x"
            qg = dist.MultivariateNormal(
                self.g_loc[..., None, :], scale_tril=self.g_scale_tril[..., None, :, :]
            )
            return x, pyro.sample("g", qg)
