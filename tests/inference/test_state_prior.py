"""The class-conditional first-state prior ``p(x_1 | g)`` of intention inference: its moments
against numpy, the first online update against GP-ADF on the GP posterior (another code path),
the batch bound against the per-value GP-ADF evidence, and what it adds on held-out movements."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.inference.filtering import filter_sequence, gp_adf_update
from hgpdm_torch.inference.intention import (
    OnlineIntentionFilter,
    batch_bound,
    class_state_prior,
    infer_intention,
    intention_grid,
)
from hgpdm_torch.models import IDDM


@pytest.fixture(scope="module")
def located():
    """Three styles of a movement, each also shifted by its own offset of the observations:
    the first frame already tells them apart."""
    data = styled_movements(3, 8, 14, 5, noise=0.02, seed=4)
    offsets = torch.tensor([[-1.5], [0.0], [1.5]], dtype=torch.float64)
    seqs = [s + offsets[int(c)] for s, c in zip(data.sequences, data.labels, strict=True)]
    train = [i for i in range(len(seqs)) if i % 4 != 3]
    test = [i for i in range(len(seqs)) if i % 4 == 3]
    torch.manual_seed(0)
    model = IDDM(
        [seqs[i] for i in train], data.labels[train], 3, intention="discrete",
        measurement="linear", alpha=(0.9, 0.3, 0.1, 1e-2),
    )  # fmt: skip
    model.fit(30, warn=False)
    z_test = torch.stack([seqs[i] for i in test])
    return model, z_test, data.labels[test]


def test_class_prior_moments_against_numpy(located):
    model, _, _ = located
    values = intention_grid(model)
    mu, Sigma = class_state_prior(model, values, torch.float64)
    x = model.latent.detach().numpy()
    codes = np.repeat(model.intention_codes().numpy(), model.lengths.numpy())
    marginal = np.cov(x.T)
    dx = x.shape[1]
    for k in range(3):
        xk = x[codes == k]
        n = len(xk)
        expected = ((n - 1) * np.cov(xk.T) + dx * marginal) / (n + dx)
        # means and covariances of n ~ 50 latent points of size ~1 by torch and numpy: sums of
        # n terms, n eps ~ 1e-14 of the scale (measured: 3e-16, 2e-15)
        np.testing.assert_allclose(mu[k].numpy(), xk.mean(0), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(Sigma[k].numpy(), expected, rtol=1e-10, atol=1e-12)


def test_first_online_update_is_the_gp_adf_evidence_of_each_class_prior(located, gp_rounding):
    """``B_1(g) = log p(g) + log q(z_1 | g)``: against GP-ADF on the measurement GP itself."""
    model, z, _ = located
    values = intention_grid(model)
    mu, Sigma = class_state_prior(model, values, torch.float64)
    f = OnlineIntentionFilter(model, batch_size=z.shape[0], state_prior="class")
    belief = f.update(z[:, 0])
    meas = model.measurement_posterior()
    _, _, ll = gp_adf_update(meas, mu[:, None], Sigma[:, None], z[None, :, 0])  # [K, B]
    # one measurement update by other code and shapes: the evidence agrees to gp_rounding of
    # its scale, and the probabilities move by that much (measured: 2e-7 of it)
    rel = gp_rounding(meas) * max(1.0, float(ll.abs().max()))
    torch.testing.assert_close(belief.prob, torch.softmax(ll.T, -1), rtol=rel, atol=rel)
    # the marginal prior leaves the first belief uniform (Algorithm 3.2, lines 1-3)
    g = OnlineIntentionFilter(model, batch_size=z.shape[0])
    torch.testing.assert_close(g.update(z[:, 0]).prob, torch.full((z.shape[0], 3), 1 / 3.0))


def test_batch_bound_with_class_priors_matches_the_per_class_filter_evidence(located):
    """Eq. 22 with each value's own first-state prior ~ the GP-ADF evidence
    ``log p(z_{1:T} | g)`` of a filter started at that prior; compared as log-evidence
    differences between values (the beliefs themselves are nearly one-hot here)."""
    model, z, _ = located
    values = intention_grid(model)
    mu, Sigma = class_state_prior(model, values, torch.float64)
    window = z[:, :4]
    trans, meas = model.transition_posterior(), model.measurement_posterior()
    bound = batch_bound(trans, meas, window, values, mu[:, None], Sigma[:, None])  # [K, W]
    ll = filter_sequence(
        trans, meas, window, mu[:, None], Sigma[:, None], g=values[:, None, :]
    ).log_likelihood  # [K, W]
    spread = (ll - ll.mean(0)).abs().max()
    assert float(spread) > 10.0  # the values are far apart in evidence
    error = (bound - bound.mean(0)) - (ll - ll.mean(0))
    assert float(error.abs().max()) < 0.03 * float(spread)  # measured: 1.7%
    # infer_intention normalises exactly this bound (uniform prior)
    batch = infer_intention(model, window, state_prior="class")
    torch.testing.assert_close(batch.log_prob, torch.log_softmax(bound.T, -1))


def test_class_prior_recognises_held_out_movements_from_their_first_frame(located):
    """Where the marginal prior's first belief is uniform (tested above), the class prior
    names every held-out movement's style from its first frame."""
    model, z, labels = located
    online = OnlineIntentionFilter(model, batch_size=z.shape[0], state_prior="class")
    first = online.update(z[:, 0]).prob
    assert bool((first.argmax(-1) == labels).all())
    assert float(first[torch.arange(len(labels)), labels].mean()) > 0.9


def test_state_prior_bad_inputs(located, continuous_iddm):
    model, z, _ = located
    with pytest.raises(ValueError, match="state_prior"):
        infer_intention(model, z, state_prior="per-class")
    with pytest.raises(ValueError, match="state_prior"):
        OnlineIntentionFilter(model, state_prior="uniform")
    with pytest.raises(ValueError, match="not both"):
        infer_intention(model, z, state_prior="class", mu0=torch.zeros(3))
    with pytest.raises(ValueError, match="discrete intention"):
        OnlineIntentionFilter(continuous_iddm, state_prior="class")
    # a code without training sequences has no class prior
    sparse = IDDM(model.sequences()[:4], [0, 0, 1, 1], 2, measurement="linear", num_values=3)
    with pytest.raises(ValueError, match="intention 2 has no training sequences"):
        infer_intention(sparse, z[:, :, :], state_prior="class")
