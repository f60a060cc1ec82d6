"""Synthetic movement generators: reproducibility, shapes, ground truth, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import styled_movements, targeted_movements


def test_styled_movements_are_seeded_and_shaped():
    a = styled_movements(3, 2, 20, 11, length_jitter=3, seed=5)
    b = styled_movements(3, 2, 20, 11, length_jitter=3, seed=5)
    c = styled_movements(3, 2, 20, 11, length_jitter=3, seed=6)
    assert len(a) == 6 and a.labels.tolist() == [0, 0, 1, 1, 2, 2]
    assert all(s.shape[1] == 11 and 17 <= s.shape[0] <= 23 for s in a.sequences)
    assert all(torch.equal(x, y) for x, y in zip(a.sequences, b.sequences, strict=True))
    assert not torch.equal(a.sequences[0][:5], c.sequences[0][:5])


def test_styles_differ_in_dynamics():
    d = styled_movements(3, 3, 40, 8, noise=0.0, seed=0)
    speed = [
        torch.stack(
            [
                (y[1:] - y[:-1]).norm(dim=-1).mean()
                for y, k in zip(d.latents, d.labels, strict=True)
                if k == s
            ]
        )
        for s in range(3)
    ]
    means = [float(v.mean()) for v in speed]
    spread = max(float(v.std()) for v in speed)
    assert min(abs(means[i] - means[j]) for i in range(3) for j in range(i)) > 3 * spread


def test_targeted_movements_reveal_target_at_the_end():
    d = targeted_movements(30, 25, 6, noise=0.0, seed=2)
    ends = torch.stack([y[-1, 0] for y in d.latents])
    corr = torch.corrcoef(torch.stack([ends, d.labels]))[0, 1]
    assert corr > 0.95
    train, test = d.split(0.3, seed=1)
    assert len(train) + len(test) == 30 and len(test) == 9


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: styled_movements(0), "num_styles"),
        (lambda: styled_movements(2, 2, 1), "length"),
        (lambda: styled_movements(2, 2, 10, 2), "obs_dim"),
        (lambda: styled_movements(noise=-1.0), "noise"),
        (lambda: targeted_movements(noise=float("nan")), "noise"),
        (lambda: targeted_movements(target_range=(1.0, 0.0)), "target_range"),
        (lambda: targeted_movements(5).split(1.5), "test_fraction"),
        # every numeric argument: finite, in range, an int where a count is meant
        (lambda: styled_movements(noise=math.inf), "noise"),
        (lambda: styled_movements(noise=math.nan), "noise"),
        (lambda: styled_movements(noise="0.1"), "noise"),
        (lambda: styled_movements(noise=1e308), "noise"),  # overflows the observations
        (lambda: styled_movements(2, 2.0), "per_style"),
        (lambda: styled_movements(True), "num_styles"),
        (lambda: styled_movements(length_jitter=-1), "length_jitter"),
        (lambda: styled_movements(length=10, length_jitter=9), "length_jitter"),
        (lambda: styled_movements(seed=-1), "seed"),
        (lambda: styled_movements(seed=2**64), "seed"),
        (lambda: targeted_movements(0), "num"),
        (lambda: targeted_movements(noise=-math.inf), "noise"),
        (lambda: targeted_movements(target_range=(0.0, math.inf)), "target_range"),
        (lambda: targeted_movements(target_range=(math.nan, 1.0)), "target_range"),
        (lambda: targeted_movements(target_range=(-1e308, 1e308)), "target_range"),
        (lambda: targeted_movements(target_range=(0.0,)), "target_range"),
        (lambda: targeted_movements(target_range=1.0), "target_range"),
        (lambda: targeted_movements(seed=-3), "seed"),
        (lambda: targeted_movements(5).split(math.nan), "test_fraction"),
        (lambda: targeted_movements(5).split(0.5, seed=-1), "seed"),
    ],
)
def test_bad_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_numpy_and_tensor_scalars_are_accepted():
    a = styled_movements(np.int64(2), torch.tensor(2), 12, 5, noise=np.float32(0.01), seed=1)
    b = styled_movements(2, 2, 12, 5, noise=float(np.float32(0.01)), seed=1)
    assert all(torch.equal(x, y) for x, y in zip(a.sequences, b.sequences, strict=True))
    assert all(bool(torch.isfinite(s).all()) for s in a.sequences)
