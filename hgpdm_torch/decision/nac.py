r"""Episodic natural actor-critic with a softmax policy: the policy-gradient baseline of Sec. 4.3.2.

The policy is a softmax over the actions available in a belief state (Sutton and Barto, 1998)
with the action-blocked features of Eq. 37::

    pi(a | theta) = exp(phi'(theta)^T Theta[a]) / sum_{b allowed} exp(phi'(theta)^T Theta[b])
    d log pi(a | theta) / d Theta[b] = (delta_{ab} - pi(b | theta)) phi'(theta)

Episodic NAC (Peters and Schaal, 2008) samples episodes with the current policy, sums the score
function over each episode, ``psi_e = sum_t grad log pi(a_t | theta_t)``, and regresses the
returns on it with a baseline, ``R_e ~= psi_e^T w + J``. With this compatible function
approximation ``w`` is the natural gradient ``F^-1 grad J``; the parameters move a fixed
distance along it, ``Theta <- Theta + alpha w / ||w||``. It is on-policy: every update needs
fresh episodes, which here are free (the reward of any start step and movement of a training
trial is in its reward table).

Shapes: ``n`` trials, ``T`` steps, ``K`` state features, ``A`` actions, ``E`` episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..progress import tqdm
from ..validation import as_tensor
from .stopping import Episodes, StoppingProblem

__all__ = ["NACResult", "SoftmaxPolicy", "natural_gradient", "nac"]


@dataclass
class SoftmaxPolicy:
    """Softmax action selection over allowed actions with linear preferences.

    Attributes:
        theta: ``[A, K]`` preference weights.
    """

    theta: torch.Tensor

    def probs(self, phi: torch.Tensor, allowed: torch.Tensor) -> torch.Tensor:
        """``[..., K]`` features and ``[..., A]`` allowed mask -> ``[..., A]`` probabilities."""
        logits = phi @ self.theta.T
        allowed = torch.as_tensor(allowed, dtype=torch.bool).expand_as(logits)
        if not bool(allowed.any(-1).all()):
            raise ValueError("every state must allow at least one action")
        return torch.softmax(logits.masked_fill(~allowed, -torch.inf), -1)

    def sample(
        self, phi: torch.Tensor, allowed: torch.Tensor, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """One action per state ``[m, K] -> [m]``, drawn from :meth:`probs`."""
        return torch.multinomial(self.probs(phi, allowed), 1, generator=generator)[:, 0]


@dataclass
class NACResult:
    """Output of :func:`nac`.

    Attributes:
        policy: the learned :class:`SoftmaxPolicy`.
        returns: ``[iterations]`` mean return of the episodes sampled at each update.
    """

    policy: SoftmaxPolicy
    returns: torch.Tensor


def _allowed(problem: StoppingProblem) -> torch.Tensor:
    return torch.stack([problem.allowed(t) for t in range(problem.horizon)])  # [T, A]


def _episode_scores(episodes: Episodes, phi: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Summed scores ``sum_{t <= tau_e} (onehot(a_t) - pi(. | theta_t)) phi'(theta_t)^T``.

    Shapes: ``phi [n, T, K]``, ``probs [n, T, A]`` -> ``[E, A, K]``.
    """
    T, A = probs.shape[1], probs.shape[2]
    steps = torch.arange(T)
    tau = episodes.stop_step[:, None]
    taken = torch.where(steps[None] < tau, 0, episodes.stop_action[:, None])  # [E, T]
    onehot = torch.nn.functional.one_hot(taken, A).to(phi.dtype)
    resid = (onehot - probs[episodes.trial]) * (steps[None] <= tau)[..., None]  # [E, T, A]
    return torch.einsum("eta,etk->eak", resid, phi[episodes.trial])


def natural_gradient(
    scores: torch.Tensor, returns: torch.Tensor, *, ridge: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor]:
    """Episodic NAC critic: least squares ``R_e ~= psi_e^T w + J`` (ridge on ``w`` only).

    Args:
        scores: ``[E, P]`` summed score functions ``psi_e``; returns: ``[E]``.
        ridge: ``lambda > 0`` added to the ``w`` block of the normal equations.

    Returns:
        the natural gradient ``w [P]`` and the baseline ``J`` (scalar tensor).
    """
    E, P = scores.shape
    X = torch.cat([scores, scores.new_ones(E, 1)], 1)
    reg = torch.full((P + 1,), ridge, dtype=scores.dtype, device=scores.device)
    reg[-1] = 0.0
    sol = torch.linalg.solve(X.T @ X / E + torch.diag(reg), X.T @ returns / E)
    return sol[:P], sol[P]


def nac(
    problem: StoppingProblem,
    phi: torch.Tensor,
    *,
    iterations: int = 100,
    episodes_per_trial: int = 4,
    step_size: float = 0.5,
    ridge: float = 1e-4,
    generator: torch.Generator | None = None,
    progress: bool = False,
) -> NACResult:
    """Learn a softmax stopping policy with episodic natural actor-critic.

    Args:
        problem: the training trials (beliefs and reward tables).
        phi: ``[n, T, K]`` state features of ``problem.beliefs`` (e.g. a fitted
            :class:`~hgpdm_torch.decision.basis.RadialBasis` applied to them).
        iterations: policy updates.
        episodes_per_trial: on-policy episodes sampled per trial and update.
        step_size: ``alpha``, the length of each step along the normalised natural gradient.
        ridge: regularisation of the critic's least squares.
        generator: random generator for the episodes.
        progress: show a tqdm bar over updates.

    Returns:
        :class:`NACResult`; the policy starts uniform over the allowed actions (``Theta = 0``).
    """
    if not isinstance(problem, StoppingProblem):
        raise TypeError(f"problem must be a StoppingProblem, got {type(problem).__name__}")
    phi = as_tensor(phi, "phi", ndim=3, dtype=problem.beliefs.dtype)
    if phi.shape[:2] != problem.beliefs.shape[:2]:
        raise ValueError(
            f"phi must have shape [n, T, K] with [n, T] = {tuple(problem.beliefs.shape[:2])}, got "
            f"{tuple(phi.shape)}"
        )
    for name, value in (("iterations", iterations), ("episodes_per_trial", episodes_per_trial)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    if not (isinstance(step_size, int | float) and step_size > 0):
        raise ValueError(f"step_size must be a positive number, got {step_size!r}")
    if not (isinstance(ridge, int | float) and ridge > 0):
        raise ValueError(f"ridge must be a positive number, got {ridge!r}")
    A, K = problem.num_actions, phi.shape[-1]
    policy = SoftmaxPolicy(phi.new_zeros(A, K))
    allowed = _allowed(problem)
    returns = []
    for _ in tqdm(range(iterations), disable=not progress, desc="NAC", leave=False):
        probs = policy.probs(phi, allowed)
        episodes = problem.sample_episodes(episodes_per_trial, probs=probs, generator=generator)
        scores = _episode_scores(episodes, phi, probs).reshape(len(episodes), A * K)
        w, _ = natural_gradient(scores, episodes.reward, ridge=ridge)
        returns.append(episodes.reward.mean())
        norm = w.norm()
        if norm > 0:
            policy = SoftmaxPolicy(policy.theta + step_size * (w / norm).reshape(A, K))
    return NACResult(policy, torch.stack(returns))
