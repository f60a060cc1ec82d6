"""Radial basis features (Eq. 37) against scipy distances and known clusters."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.distance import cdist

from hgpdm_torch.decision.basis import RadialBasis, action_features


def _clusters(gen: torch.Generator, per: int = 200):
    means = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0], [0.0, 0.0, 5.0]])
    x = means.repeat_interleave(per, 0) + 0.1 * torch.randn(4 * per, 3, generator=gen)
    return means, x


def test_features_match_the_formula(generator):
    x = torch.randn(300, 4, generator=generator) * torch.tensor([1.0, 10.0, 0.1, 3.0])
    basis = RadialBasis(12, seed=3).fit(x)
    z = ((x - x.mean(0)) / x.std(0, correction=0)).numpy()
    c = basis.centres.numpy()
    d2 = cdist(z, c, "sqeuclidean")
    off = cdist(c, c, "sqeuclidean")[~np.eye(12, dtype=bool)]
    assert basis.eta == pytest.approx(1.0 / np.median(off))
    np.testing.assert_allclose(basis(x).numpy(), np.exp(-basis.eta * d2), rtol=1e-12, atol=1e-14)
    # leading batch dims
    assert basis(x.view(3, 100, 4)).shape == (3, 100, 12)


def test_kmeans_centres_find_the_clusters(generator):
    means, x = _clusters(generator)
    basis = RadialBasis(4, standardize=False).fit(x)
    d = torch.cdist(basis.centres, means)
    assert (d.min(0).values < 0.05).all()  # every cluster has a centre at its mean (SE 0.007)


def test_few_distinct_states_become_the_centres():
    states = torch.tensor([[0.0, 1.0], [2.0, 3.0], [0.0, 1.0], [5.0, 5.0]])
    basis = RadialBasis(10, standardize=False, eta=50.0).fit(states)
    assert basis.num_features == 3
    phi = basis(states)
    torch.testing.assert_close(phi.max(-1).values, torch.ones(4))
    assert ((phi > 0.5).sum(-1) == 1).all()


def test_standardisation_is_invariant_to_scale_and_shift(generator):
    x = torch.randn(200, 3, generator=generator)
    y = x * torch.tensor([1e3, 1.0, 1e-2]) + torch.tensor([5.0, -2.0, 100.0])
    a = RadialBasis(8, seed=0).fit(x)
    b = RadialBasis(8, seed=0).fit(y)
    torch.testing.assert_close(a(x), b(y), rtol=1e-6, atol=1e-9)


def test_bias_feature(generator):
    x = torch.randn(50, 2, generator=generator)
    basis = RadialBasis(5, bias=True).fit(x)
    phi = basis(x)
    assert basis.num_features == 6 and torch.equal(phi[:, -1], torch.ones(50))


def test_action_blocked_layout():
    phi = torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    out = action_features(phi, torch.tensor([0, 2, 1]), 3)
    expected = torch.tensor(
        [[1.0, 2.0, 0, 0, 0, 0], [0, 0, 0, 0, 3.0, 4.0], [0, 0, 5.0, 6.0, 0, 0]]
    )
    torch.testing.assert_close(out, expected)
    w = torch.arange(6.0)
    torch.testing.assert_close(out @ w, (phi * w.view(3, 2)[[0, 2, 1]]).sum(-1))


def test_bad_input(generator):
    with pytest.raises(ValueError, match="num_centres"):
        RadialBasis(0)
    with pytest.raises(ValueError, match="eta"):
        RadialBasis(3, eta=-1.0)
    basis = RadialBasis(3)
    with pytest.raises(RuntimeError, match="not fitted"):
        basis(torch.zeros(2, 2))
    with pytest.raises(ValueError, match="2 dimensions"):
        basis.fit(torch.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        basis.fit(torch.tensor([[0.0, float("nan")]]))
    basis.fit(torch.randn(20, 2, generator=generator))
    with pytest.raises(ValueError, match="F = 2"):
        basis(torch.zeros(4, 3))
    with pytest.raises(ValueError, match="action must be in"):
        action_features(torch.ones(2, 3), torch.tensor([0, 4]), 4)
    with pytest.raises(TypeError, match="integers"):
        action_features(torch.ones(2, 3), torch.tensor([0.0, 1.0]), 4)
    with pytest.raises(ValueError, match="batch shape"):
        action_features(torch.ones(2, 3), torch.tensor([0]), 4)
