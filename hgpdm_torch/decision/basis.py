r"""Radial basis features of belief states and their action-blocked layout (thesis Eq. 37).

The value function is approximated linearly, ``Q(theta, a) ~= phi(theta, a)^T w`` (Sec. 4.2.5),
with radial basis functions centred on K-means centres of the belief states met in training::

    phi'(theta) = [exp(-eta ||theta - c_1||^2), ..., exp(-eta ||theta - c_K||^2)]        (Eq. 37)
    phi(theta, a) = [delta_{a,0} phi'(theta)^T, ..., delta_{a,|A|-1} phi'(theta)^T]^T

The belief vector mixes latent means, covariances and histogram probabilities on different
scales, so by default each coordinate is standardised with the training mean and standard
deviation before clustering and before distances are taken. An optional constant feature
(``bias``) lets the approximation represent a value far from every centre; the thesis uses the
RBFs alone (``bias=False``).

Shapes: ``M`` states, ``F`` belief features, ``K`` centres, ``A`` actions.
"""

from __future__ import annotations

import numpy as np
import torch
from sklearn.cluster import KMeans

from ..tiling import OpCount, exp_
from ..validation import as_tensor

__all__ = ["MomentBasis", "RadialBasis", "action_features"]


class RadialBasis:
    """Gaussian radial basis functions on K-means centres of belief states (Eq. 37).

    Args:
        num_centres: K; capped at the number of distinct training states.
        eta: inverse squared width ``eta``; default ``1 / median ||c_i - c_j||^2`` over pairs of
            centres (in standardised coordinates), or 1 for a single centre.
        standardize: z-score each coordinate with the training statistics first.
        bias: append a constant 1 to ``phi'``.
        seed: seed of the K-means initialisation.

    Attributes (after :meth:`fit`):
        centres: ``[K, F]`` centres in standardised coordinates.
        eta: the width actually used.
    """

    def __init__(
        self,
        num_centres: int = 100,
        *,
        eta: float | None = None,
        standardize: bool = True,
        bias: bool = False,
        seed: int = 0,
    ) -> None:
        if isinstance(num_centres, bool) or not isinstance(num_centres, int) or num_centres < 1:
            raise ValueError(f"num_centres must be a positive int, got {num_centres!r}")
        if eta is not None and not (isinstance(eta, int | float) and np.isfinite(eta) and eta > 0):
            raise ValueError(f"eta must be a positive finite number or None, got {eta!r}")
        self.num_centres = num_centres
        self.eta = None if eta is None else float(eta)
        self._eta_given = eta is not None
        self.standardize = bool(standardize)
        self.bias = bool(bias)
        self.seed = int(seed)
        self.centres: torch.Tensor | None = None

    def fit(self, states: torch.Tensor) -> RadialBasis:
        """Choose the centres by K-means on ``states [M, F]`` (scikit-learn); returns ``self``."""
        x = as_tensor(states, "states", ndim=2)
        if x.shape[0] == 0:
            raise ValueError("states must hold at least one belief state")
        self.mean = x.mean(0) if self.standardize else torch.zeros_like(x[0])
        std = x.std(0, correction=0) if self.standardize else torch.ones_like(x[0])
        self.std = torch.where(std > 1e-12, std, torch.ones_like(std))
        z = ((x - self.mean) / self.std).detach().cpu().numpy()
        distinct = np.unique(z, axis=0)
        k = min(self.num_centres, len(distinct))
        if k == len(distinct):  # K-means' optimum: every distinct state is a centre
            centres = distinct
        else:
            centres = KMeans(n_clusters=k, n_init=4, random_state=self.seed).fit(z).cluster_centers_
        self.centres = torch.as_tensor(centres, dtype=x.dtype, device=x.device)
        if not self._eta_given:
            if k == 1:
                self.eta = 1.0
            else:
                d2 = torch.cdist(self.centres, self.centres).pow(2)
                off = d2[~torch.eye(k, dtype=torch.bool, device=x.device)]
                self.eta = float(1.0 / off.quantile(0.5).clamp_min(1e-12))
        return self

    @property
    def num_features(self) -> int:
        """Length of ``phi'``: K (+1 with ``bias``)."""
        if self.centres is None:
            raise RuntimeError("RadialBasis is not fitted; call fit(states) first")
        return self.centres.shape[0] + int(self.bias)

    def operations(self, num: int) -> OpCount:
        """Work of :meth:`__call__` on ``num`` states (a floor's count): the standardisation
        (``F``), the squared distances to the K centres (``K (F + 1)``) and ``K``
        exponentials per state."""
        if self.centres is None:
            raise RuntimeError("RadialBasis is not fitted; call fit(states) first")
        k, f = self.centres.shape
        return OpCount(exps=k, madds=f + k * (f + 1)) * num

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """``phi'(theta)`` of Eq. 37: ``states [..., F] -> [..., K (+1)]``."""
        if self.centres is None:
            raise RuntimeError("RadialBasis is not fitted; call fit(states) first")
        x = as_tensor(states, "states", min_ndim=1, dtype=self.centres.dtype)
        if x.shape[-1] != self.centres.shape[-1]:
            raise ValueError(
                f"states must have F = {self.centres.shape[-1]} features (as in fit), got "
                f"{x.shape[-1]}"
            )
        z = (x.to(self.centres.device) - self.mean) / self.std
        lead, z = z.shape[:-1], z.reshape(-1, z.shape[-1])
        # -eta |z - c|^2 = -eta (|z|^2 + |c|^2) + 2 eta z.c: one GEMM, as cdist forms it for
        # more than 25 rows, without its square root and square; rounding can push the
        # expansion above 0 where z ~ c, hence the clamp
        c = self.centres
        norms = z.pow(2).sum(-1, keepdim=True) + c.pow(2).sum(-1)
        exponent = torch.addmm(norms, z, c.T, beta=-self.eta, alpha=2.0 * self.eta)
        phi = exp_(exponent.clamp_max_(0.0)).reshape(*lead, -1)
        if self.bias:
            phi = torch.cat([phi, torch.ones_like(phi[..., :1])], -1)
        return phi


class MomentBasis:
    """Per decision step, a polynomial in the belief's mean and standard deviation of the target.

    Takes the ``[..., 2 + T]`` vectors of :func:`~hgpdm_torch.decision.sources.moment_vector`
    (mean ``m``, sd ``s``, one-hot step) and returns, in the block of the vector's step, every
    monomial ``m^i s^j`` with ``i + j <= degree`` (a constant included): ``phi'(theta)`` of
    ``T (degree + 1) (degree + 2) / 2`` features. A movement's stopping value is the chance that
    the target lies where the movement returns the ball, which moves with the mean and flattens
    with the spread, and differently at each start time: a low-degree polynomial per step
    represents it with few weights, where RBFs on the histogram (Eq. 37) need many centres.

    Args:
        num_steps: T, decision steps.
        degree: the polynomial degree (default 3).
    """

    def __init__(self, num_steps: int, degree: int = 3) -> None:
        for name, value in (("num_steps", num_steps), ("degree", degree)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        self.num_steps, self.degree = num_steps, degree
        self._powers = [(i, d - i) for d in range(degree + 1) for i in range(d, -1, -1)]

    def fit(self, states: torch.Tensor) -> MomentBasis:
        """Nothing to learn (the polynomial is fixed); checks the width. Returns ``self``."""
        self(states)
        return self

    @property
    def num_features(self) -> int:
        """Length of ``phi'``: ``T (degree + 1) (degree + 2) / 2``."""
        return self.num_steps * len(self._powers)

    def __call__(self, states: torch.Tensor) -> torch.Tensor:
        """``[..., 2 + T] -> [..., num_features]``."""
        x = as_tensor(states, "states", min_ndim=1)
        if x.shape[-1] != 2 + self.num_steps:
            raise ValueError(
                f"states must have 2 + T = {2 + self.num_steps} entries (mean, sd, one-hot "
                f"step), got {x.shape[-1]}"
            )
        m, s, step = x[..., :1], x[..., 1:2], x[..., 2:]
        mono = torch.cat([m**i * s**j for i, j in self._powers], -1)
        return (step[..., :, None] * mono[..., None, :]).flatten(-2)


def action_features(phi: torch.Tensor, action: torch.Tensor, num_actions: int) -> torch.Tensor:
    """The action-blocked features ``phi(theta, a)`` of Eq. 37.

    Args:
        phi: ``[..., K]`` state features ``phi'(theta)``.
        action: ``[...]`` integer actions in ``0 .. num_actions - 1``.
        num_actions: ``|A|``.

    Returns:
        ``[..., num_actions * K]``: block ``a`` holds ``phi`` where ``action == a``, else zeros.
    """
    if isinstance(num_actions, bool) or not isinstance(num_actions, int) or num_actions < 1:
        raise ValueError(f"num_actions must be a positive int, got {num_actions!r}")
    action = torch.as_tensor(action)
    if action.is_floating_point() or action.dtype == torch.bool:
        raise TypeError(f"action must hold integers, got {action.dtype}")
    if action.shape != phi.shape[:-1]:
        raise ValueError(
            f"action must have the batch shape of phi {tuple(phi.shape[:-1])}, got "
            f"{tuple(action.shape)}"
        )
    if bool(((action < 0) | (action >= num_actions)).any()):
        raise ValueError(f"action must be in 0 .. {num_actions - 1}")
    onehot = torch.nn.functional.one_hot(action.long(), num_actions).to(phi.dtype)
    return (onehot[..., :, None] * phi[..., None, :]).flatten(-2)
