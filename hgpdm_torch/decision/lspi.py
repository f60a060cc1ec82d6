r"""Least-squares policy iteration for the optimal stopping problem (thesis Algorithm 4.1).

With the action-blocked features of Eq. 37, ``Q(theta, a) = phi'(theta)^T W[a]``. Given samples
``(theta_l, a_l, r_l, theta'_l)`` and the greedy policy ``pi`` of the current weights, LSTDQ
(Lagoudakis and Parr, 2003) solves

    A = 1/L sum_l phi(theta_l, a_l) (phi(theta_l, a_l) - gamma phi(theta'_l, pi(theta'_l)))^T
    b = 1/L sum_l phi(theta_l, a_l) r_l,          w = (A + delta I)^-1 b          (Alg. 4.1, l. 8)

and policy iteration repeats this with the improved greedy policy until the policy on the next
states stops changing (or an iteration cap). Stopping actions are absorbing: their next-state
term is zero, so ``Q(theta, a != 0)`` is fitted to the observed rewards directly, and the waiting
action bootstraps on ``max`` over the actions available in ``theta'`` (stops only at the last
step). The problem has a finite horizon, so the default discount is 1, as in the thesis.

The feature matrix is block-sparse (one non-zero block per sample), so ``A`` is assembled per
(action, next action) pair: ``O(L K^2 A)`` work instead of ``O(L K^2 A^2)``.

Shapes: ``L`` samples, ``K`` state features, ``A`` actions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..progress import tqdm
from ..validation import as_tensor
from .stopping import Transitions

__all__ = ["LSPIResult", "LinearQ", "lspi", "lstdq"]


@dataclass
class LinearQ:
    """A linear state-action value function ``Q(theta, a) = phi'(theta)^T weights[a]``.

    Attributes:
        weights: ``[A, K]``.
    """

    weights: torch.Tensor

    def values(self, phi: torch.Tensor) -> torch.Tensor:
        """``[..., K]`` state features -> ``[..., A]`` action values."""
        if phi.shape[-1] != self.weights.shape[-1]:
            raise ValueError(
                f"phi must have K = {self.weights.shape[-1]} features, got {phi.shape[-1]}"
            )
        return phi @ self.weights.T

    def greedy(self, phi: torch.Tensor, allowed: torch.Tensor | None = None) -> torch.Tensor:
        """``argmax_a Q`` over the ``allowed [..., A]`` actions (default all): ``[...]``.

        Rows with no allowed action (absorbing states) return -1.
        """
        q = self.values(phi)
        if allowed is None:
            return q.argmax(-1)
        allowed = torch.as_tensor(allowed, dtype=torch.bool).expand_as(q)
        a = q.masked_fill(~allowed, -torch.inf).argmax(-1)
        return torch.where(allowed.any(-1), a, torch.full_like(a, -1))


@dataclass
class LSPIResult:
    """Output of :func:`lspi`.

    Attributes:
        q: the learned :class:`LinearQ`.
        iterations: policy-iteration steps run.
        converged: whether the greedy policy on the sampled next states stopped changing.
    """

    q: LinearQ
    iterations: int
    converged: bool


def _check_samples(
    phi: torch.Tensor,
    action: torch.Tensor,
    reward: torch.Tensor,
    next_phi: torch.Tensor,
    next_allowed: torch.Tensor,
) -> tuple[torch.Tensor, ...]:
    phi = as_tensor(phi, "phi", ndim=2)
    L, K = phi.shape
    if L == 0:
        raise ValueError("phi must hold at least one sample")
    next_phi = as_tensor(next_phi, "next_phi", ndim=2, dtype=phi.dtype)
    reward = as_tensor(reward, "reward", ndim=1, dtype=phi.dtype)
    action = torch.as_tensor(action)
    if action.is_floating_point() or action.dtype == torch.bool:
        raise TypeError(f"action must hold integers, got {action.dtype}")
    next_allowed = torch.as_tensor(next_allowed)
    if next_allowed.dtype != torch.bool or next_allowed.dim() != 2:
        raise TypeError("next_allowed must be a [L, A] bool tensor")
    A = next_allowed.shape[1]
    if next_phi.shape != (L, K) or reward.shape != (L,) or action.shape != (L,):
        raise ValueError(
            f"phi [L, K] = {tuple(phi.shape)} needs next_phi [L, K], reward [L] and action [L]; "
            f"got {tuple(next_phi.shape)}, {tuple(reward.shape)}, {tuple(action.shape)}"
        )
    if next_allowed.shape[0] != L:
        raise ValueError(f"next_allowed must have L = {L} rows, got {next_allowed.shape[0]}")
    if bool(((action < 0) | (action >= A)).any()):
        raise ValueError(f"action must be in 0 .. {A - 1} (next_allowed has A = {A} columns)")
    return phi, action.long(), reward, next_phi, next_allowed


def lstdq(
    phi: torch.Tensor,
    action: torch.Tensor,
    reward: torch.Tensor,
    next_phi: torch.Tensor,
    next_action: torch.Tensor,
    num_actions: int,
    *,
    ridge: float = 1e-6,
    discount: float = 1.0,
) -> torch.Tensor:
    """LSTDQ: the weights ``[A, K]`` of ``Q^pi`` for the next actions ``pi(theta')``.

    Args:
        phi: ``[L, K]`` features of ``theta``; action: ``[L]``; reward: ``[L]``.
        next_phi: ``[L, K]`` features of ``theta'``.
        next_action: ``[L]`` ``pi(theta')``, or -1 where ``theta'`` is absorbing.
        num_actions: A.
        ridge: ``delta`` added to the diagonal of ``A`` (Alg. 4.1, line 8).
        discount: ``gamma``.
    """
    if phi.dim() != 2 or next_phi.shape != phi.shape:
        raise ValueError(f"phi and next_phi must both be [L, K], got {phi.shape}, {next_phi.shape}")
    L, K = phi.shape
    A = num_actions
    if not isinstance(A, int) or A < 1:
        raise ValueError(f"num_actions must be a positive int, got {num_actions!r}")
    for name, t in (("action", action), ("next_action", next_action), ("reward", reward)):
        if t.shape != (L,):
            raise ValueError(f"{name} must have shape [{L}], got {tuple(t.shape)}")
    if bool(((action < 0) | (action >= A)).any()):
        raise ValueError(f"action must be in 0 .. {A - 1}")
    if bool(((next_action < -1) | (next_action >= A)).any()):
        raise ValueError(f"next_action must be in -1 .. {A - 1} (-1: absorbing)")
    if not ridge > 0 or not 0 < discount <= 1:
        raise ValueError(f"need ridge > 0 and discount in (0, 1], got {ridge}, {discount}")
    gram = phi.new_zeros(A, K, A, K)
    for a in range(A):
        rows = action == a
        if bool(rows.any()):
            pa = phi[rows]
            gram[a, :, a, :] += pa.T @ pa
            for b in range(A):
                nb = rows & (next_action == b)
                if bool(nb.any()):
                    gram[a, :, b, :] -= discount * (phi[nb].T @ next_phi[nb])
    rhs = phi.new_zeros(A, K).index_add_(0, action, phi * reward[:, None])
    mat = gram.reshape(A * K, A * K) / L
    mat = mat + ridge * torch.eye(A * K, dtype=phi.dtype, device=phi.device)
    return torch.linalg.solve(mat, rhs.reshape(A * K) / L).reshape(A, K)


def lspi(
    phi: torch.Tensor | Transitions,
    action: torch.Tensor | None = None,
    reward: torch.Tensor | None = None,
    next_phi: torch.Tensor | None = None,
    next_allowed: torch.Tensor | None = None,
    *,
    features: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ridge: float = 1e-6,
    discount: float = 1.0,
    max_iter: int = 50,
    progress: bool = False,
) -> LSPIResult:
    """Least-squares policy iteration (Algorithm 4.1) from a fixed set of samples.

    Call either with feature arrays ``lspi(phi, action, reward, next_phi, next_allowed)`` or with
    :class:`~hgpdm_torch.decision.stopping.Transitions` and a state feature map,
    ``lspi(transitions, features=basis)`` (e.g. a fitted
    :class:`~hgpdm_torch.decision.basis.RadialBasis`).

    Args:
        phi: ``[L, K]`` state features of ``theta_l`` (or ``Transitions``).
        action: ``[L]`` actions taken.
        reward: ``[L]`` rewards.
        next_phi: ``[L, K]`` state features of ``theta'_l`` (ignored where absorbing).
        next_allowed: ``[L, A]`` actions available in ``theta'_l``; an all-False row is absorbing.
        features: state feature map ``[..., F] -> [..., K]`` (with ``Transitions``).
        ridge: ``delta > 0`` regularising the LSTDQ solve.
        discount: ``gamma`` in ``(0, 1]``.
        max_iter: cap on policy-iteration steps.
        progress: show a tqdm bar over iterations.

    Returns:
        :class:`LSPIResult`. Starts from ``w = 0`` as Algorithm 4.1 does (ties go to the first
        allowed action, i.e. waiting).
    """
    if isinstance(phi, Transitions):
        if features is None:
            raise ValueError("lspi(transitions) needs features, the state feature map")
        tr = phi
        phi, action, reward = features(tr.state), tr.action, tr.reward
        next_phi, next_allowed = features(tr.next_state), tr.next_allowed
    elif any(v is None for v in (action, reward, next_phi, next_allowed)):
        raise ValueError("lspi needs phi, action, reward, next_phi and next_allowed")
    phi, action, reward, next_phi, next_allowed = _check_samples(
        phi, action, reward, next_phi, next_allowed
    )
    if not (isinstance(ridge, int | float) and ridge > 0):
        raise ValueError(f"ridge must be a positive number, got {ridge!r}")
    if not (isinstance(discount, int | float) and 0 < discount <= 1):
        raise ValueError(f"discount must be in (0, 1], got {discount!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive int, got {max_iter!r}")
    A, K = next_allowed.shape[1], phi.shape[1]
    q = LinearQ(phi.new_zeros(A, K))
    next_action = q.greedy(next_phi, next_allowed)
    converged, iterations = False, 0
    for _ in tqdm(range(max_iter), disable=not progress, desc="LSPI", leave=False):
        w = lstdq(phi, action, reward, next_phi, next_action, A, ridge=ridge, discount=discount)
        q, iterations = LinearQ(w), iterations + 1
        improved = q.greedy(next_phi, next_allowed)
        if torch.equal(improved, next_action):  # policy stable: w is its fixed point
            converged = True
            break
        next_action = improved
    return LSPIResult(q, iterations, converged)
