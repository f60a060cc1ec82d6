"""Seeded generators of synthetic movements with a known exogenous variable.

Both generators draw a low-dimensional latent movement whose dynamics depend on g, then lift it to
``Dz`` observed dimensions with a fixed random nonlinear map ``z = A tanh(B y + c)`` plus Gaussian
noise, so that a latent-variable model has something to recover:

- :func:`styled_movements`: a discrete style (frequency, amplitude and shape of a cyclic movement,
  like a gait) per sequence;
- :func:`targeted_movements`: a continuous target (the end point of a reaching or hitting
  movement) per sequence.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass, field

import torch

__all__ = ["MovementSet", "styled_movements", "targeted_movements"]

_MAX_SEED = 2**64 - 1  # torch.Generator.manual_seed's range


@dataclass
class MovementSet:
    """Synthetic movements with ground truth.

    Attributes:
        sequences: J observed sequences ``[T_j, Dz]``.
        labels: ``[J]`` style codes (long) or targets (float).
        latents: J ground-truth latent trajectories ``[T_j, 3]``.
        kind: ``"discrete"`` or ``"continuous"``.
    """

    sequences: list[torch.Tensor]
    labels: torch.Tensor
    latents: list[torch.Tensor]
    kind: str
    info: dict[str, float] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.sequences)

    def split(self, test_fraction: float = 0.25, seed: int = 0) -> tuple[MovementSet, MovementSet]:
        """Random train/test split (stratified by style for discrete labels).

        Every style (or, for continuous labels, the whole set) puts ``round(test_fraction * n)``
        of its ``n`` sequences into the test part, but at least one and at most ``n - 1``: both
        parts hold every style.

        Raises:
            ValueError: ``test_fraction`` not in ``(0, 1)``, a bad ``seed``, or a style (or, for
                continuous labels, the set) with fewer than 2 sequences, which cannot be in
                both parts.
        """
        if not 0 < _number("test_fraction", test_fraction) < 1:
            raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
        seed = _check("seed", seed, 0, _MAX_SEED)
        gen = torch.Generator().manual_seed(seed)
        test: list[int] = []
        if self.kind == "discrete":
            styles = self.labels.unique().tolist()
            groups = [torch.nonzero(self.labels == k).flatten() for k in styles]
            for k, idx in zip(styles, groups, strict=True):
                if len(idx) < 2:
                    raise ValueError(
                        f"split needs at least 2 sequences of every style (one to train on, one "
                        f"to test), but style {k} has {len(idx)}"
                    )
        else:
            groups = [torch.arange(len(self))]
            if len(self) < 2:
                raise ValueError(f"split needs at least 2 sequences, got {len(self)}")
        for idx in groups:
            perm = idx[torch.randperm(len(idx), generator=gen)]
            take = min(max(1, round(test_fraction * len(idx))), len(idx) - 1)
            test += perm[:take].tolist()
        train = [i for i in range(len(self)) if i not in set(test)]

        def take(ids: list[int]) -> MovementSet:
            return MovementSet(
                [self.sequences[i] for i in ids],
                self.labels[ids],
                [self.latents[i] for i in ids],
                self.kind,
                dict(self.info),
            )

        return take(train), take(sorted(test))


def _check(name: str, value: int, low: int, high: int | None = None) -> int:
    """``value`` (a Python or numpy int, or a 0-dim integer tensor) as an int in ``[low, high]``."""
    try:
        number = None if isinstance(value, bool) else operator.index(value)
    except TypeError:
        number = None
    if number is None or number < low or (high is not None and number > high):
        bound = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise ValueError(f"{name} must be an int {bound}, got {value!r}")
    return number


def _number(name: str, value: float) -> float:
    """``value`` as a finite float."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool | str | bytes) or not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return number


def _check_noise(noise: float) -> float:
    if not _number("noise", noise) >= 0:
        raise ValueError(f"noise must be >= 0, got {noise}")
    return float(noise)


def _lift(latents: list[torch.Tensor], obs_dim: int, noise: float, gen: torch.Generator):
    """Map ``[T, 3]`` latents to ``[T, obs_dim]`` by a random tanh layer plus noise."""
    hidden = max(obs_dim, 8)
    b = torch.randn(hidden, 3, generator=gen, dtype=torch.float64) * 0.8
    c = torch.randn(hidden, generator=gen, dtype=torch.float64) * 0.3
    a = torch.randn(obs_dim, hidden, generator=gen, dtype=torch.float64) / math.sqrt(hidden)
    out = []
    for y in latents:
        z = torch.tanh(y @ b.T + c) @ a.T
        z = z + noise * torch.randn(z.shape, generator=gen, dtype=torch.float64)
        if not torch.isfinite(z).all():
            raise ValueError(f"noise {noise} is too large: the observations overflow")
        out.append(z)
    return out


def styled_movements(
    num_styles: int = 3,
    per_style: int = 4,
    length: int = 60,
    obs_dim: int = 12,
    *,
    noise: float = 0.02,
    length_jitter: int = 0,
    seed: int = 0,
) -> MovementSet:
    """Cyclic movements whose dynamics depend on a discrete style.

    Style k moves on a closed curve ``(r_k cos th, r_k sin th, a_k sin(2 th + phi_k))`` with phase
    increment ``omega_k`` per frame; sequences of one style differ by their start phase and a 5%
    jitter of omega. Styles differ in frequency, amplitude and shape, as gaits do.

    Args:
        num_styles: K >= 1.
        per_style: sequences per style.
        length: frames per sequence (>= 2).
        obs_dim: Dz >= 3.
        noise: standard deviation of the observation noise.
        length_jitter: sequence lengths are drawn uniformly from ``length +- length_jitter``.
        seed: random seed (a non-negative int).

    Returns:
        A :class:`MovementSet` with ``labels`` the style codes ``[J]`` (long).

    Raises:
        ValueError: an argument outside its range above, or not finite.
    """
    num_styles = _check("num_styles", num_styles, 1)
    per_style = _check("per_style", per_style, 1)
    length = _check("length", length, 2)
    obs_dim = _check("obs_dim", obs_dim, 3)
    length_jitter = _check("length_jitter", length_jitter, 0)
    seed = _check("seed", seed, 0, _MAX_SEED)
    if not length_jitter < length - 1:
        raise ValueError(f"length_jitter must be in [0, length - 2], got {length_jitter}")
    noise = _check_noise(noise)
    gen = torch.Generator().manual_seed(seed)
    omegas = torch.linspace(0.15, 0.45, num_styles, dtype=torch.float64)
    radii = torch.linspace(1.0, 0.6, num_styles, dtype=torch.float64)
    shapes = torch.linspace(0.2, 0.8, num_styles, dtype=torch.float64)
    phis = torch.linspace(0.0, math.pi, num_styles, dtype=torch.float64)
    latents, labels = [], []
    for k in range(num_styles):
        for _ in range(per_style):
            t_len = length + int(
                torch.randint(-length_jitter, length_jitter + 1, (), generator=gen)
            )
            omega = omegas[k] * (1 + 0.05 * torch.randn((), generator=gen, dtype=torch.float64))
            th0 = 2 * math.pi * torch.rand((), generator=gen, dtype=torch.float64)
            th = th0 + omega * torch.arange(t_len, dtype=torch.float64)
            y = torch.stack(
                [radii[k] * th.cos(), radii[k] * th.sin(), shapes[k] * (2 * th + phis[k]).sin()], -1
            )
            latents.append(y)
            labels.append(k)
    seqs = _lift(latents, obs_dim, noise, gen)
    return MovementSet(seqs, torch.tensor(labels), latents, "discrete", {"noise": noise})


def targeted_movements(
    num: int = 24,
    length: int = 30,
    obs_dim: int = 10,
    *,
    target_range: tuple[float, float] = (-1.0, 1.0),
    noise: float = 0.02,
    seed: int = 0,
) -> MovementSet:
    """Point-to-point movements whose end point is a continuous target g.

    The latent follows a minimum-jerk profile ``s(t)`` from a common start to ``(g, 1)`` along a
    path bent sideways in proportion to g, with a third coordinate that swings with the speed:
    early frames are alike, later ones reveal the target (as a stroke reveals where it aims).

    Args:
        num: number of sequences J.
        length: frames per sequence.
        obs_dim: Dz >= 3.
        target_range: ``(low, high)`` of the uniformly drawn targets.
        noise: standard deviation of the observation noise.
        seed: random seed (a non-negative int).

    Returns:
        A :class:`MovementSet` with ``labels`` the targets ``[J]`` (float64).

    Raises:
        ValueError: an argument outside its range above, or not finite.
    """
    num = _check("num", num, 1)
    length = _check("length", length, 2)
    obs_dim = _check("obs_dim", obs_dim, 3)
    seed = _check("seed", seed, 0, _MAX_SEED)
    noise = _check_noise(noise)
    try:
        bounds = [_number("target_range", v) for v in target_range]
    except TypeError:  # not a sequence
        bounds = []
    if isinstance(target_range, str) or len(bounds) != 2:
        raise ValueError(f"target_range must be (low, high), got {target_range!r}")
    low, high = bounds
    if not (low < high and math.isfinite(high - low)):
        raise ValueError(f"target_range must be (low, high) with low < high, got {target_range}")
    gen = torch.Generator().manual_seed(seed)
    targets = low + (high - low) * torch.rand(num, generator=gen, dtype=torch.float64)
    tau = torch.linspace(0, 1, length, dtype=torch.float64)
    s = 10 * tau**3 - 15 * tau**4 + 6 * tau**5  # minimum-jerk progress
    ds = 30 * tau**2 - 60 * tau**3 + 30 * tau**4
    latents = []
    for g in targets:
        jitter = 0.03 * torch.randn(3, generator=gen, dtype=torch.float64)
        y = torch.stack([g * s + 0.3 * g * torch.sin(math.pi * s), s, 0.5 * ds * (1 + 0.3 * g)], -1)
        latents.append(y + jitter)
    seqs = _lift(latents, obs_dim, noise, gen)
    return MovementSet(seqs, targets, latents, "continuous", {"noise": noise})
