"""Gaussian algebra (hgpdm_torch.gaussian) against independent oracles.

Oracles: scipy.stats.multivariate_normal (log-density, entropy), torch.distributions'
kl_divergence, Monte Carlo with a tolerance from its standard error and closed-form scalar cases
(expected log-density), dense numpy formulas with explicit inverses (conditioning, the RTS step
as a linear-Gaussian model), and a brute-force loop over components (mixture moments).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from torch.distributions import MultivariateNormal, kl_divergence

import hgpdm_torch.inference as inference
from hgpdm_torch import gaussian as G
from hgpdm_torch.linalg import CholeskyError


def _spd(gen: torch.Generator, *shape: int) -> torch.Tensor:
    """Random SPD matrices ``[*shape[:-1], n, n]`` (well conditioned)."""
    n = shape[-1]
    a = torch.randn(*shape[:-1], n, n, generator=gen)
    return a @ a.mT / n + 0.3 * torch.eye(n)


def test_log_2pi_is_the_one_constant():
    assert G.LOG_2PI == math.log(2.0 * math.pi)
    assert G.log_density_terms(torch.tensor(0.0), 0.0, 2) == pytest.approx(-math.log(2 * math.pi))


def test_log_density_matches_scipy_with_broadcasting(generator):
    S = _spd(generator, 3, 4)  # [3, 4, 4]
    L = torch.linalg.cholesky(S)
    mean = torch.randn(3, 4, generator=generator)
    x = torch.randn(5, 3, 4, generator=generator)  # broadcasts against the 3 Gaussians
    got = G.log_density(x, mean, L)
    assert got.shape == (5, 3)
    for j in range(3):
        ref = stats.multivariate_normal(mean[j].numpy(), S[j].numpy()).logpdf(x[:, j].numpy())
        # another factorisation (scipy: eigh) of a 4 x 4 matrix of condition number < ~20:
        # n^2 cond eps ~ 1e-13 of the log-density's terms, themselves ~ its size
        np.testing.assert_allclose(got[:, j].numpy(), ref, rtol=1e-12)


def test_log_density_rejects_bad_shapes(generator):
    L = torch.linalg.cholesky(_spd(generator, 3))
    with pytest.raises(ValueError, match="x must have shape"):
        G.log_density(torch.zeros(2), torch.zeros(3), L)
    with pytest.raises(ValueError, match="mean must have shape"):
        G.log_density(torch.zeros(3), torch.zeros(4), L)
    with pytest.raises(ValueError, match="scale_tril must have shape"):
        G.log_density(torch.zeros(3), torch.zeros(3), torch.zeros(3, 2))
    with pytest.raises(TypeError, match="scale_tril must be a torch.Tensor"):
        G.entropy(np.eye(3))


def test_entropy_matches_scipy_and_torch(generator):
    S = _spd(generator, 2, 5)
    L = torch.linalg.cholesky(S)
    got = G.entropy(L)
    ref = [stats.multivariate_normal(np.zeros(5), S[b].numpy()).entropy() for b in range(2)]
    np.testing.assert_allclose(got.numpy(), ref, rtol=1e-12)  # as above: a log-determinant
    torch.testing.assert_close(got, MultivariateNormal(torch.zeros(5), S).entropy())
    # the sign of the factor's diagonal does not matter (L diag(+-1) is a factor of S too)
    flip = L * torch.tensor([1.0, -1.0, 1.0, -1.0, -1.0])
    torch.testing.assert_close(G.entropy(flip), got, rtol=0, atol=0)  # log |L_ii|: exact


def test_expected_log_density_closed_form_scalar():
    # x ~ N(mu, t^2): E[log N(x; m, s^2)] = -1/2 (log(2 pi s^2) + ((mu - m)^2 + t^2) / s^2)
    mu, t, m, s = 0.7, 0.4, -0.2, 1.3
    got = G.expected_log_density(
        torch.tensor([mu]), torch.tensor([[t]]), torch.tensor([m]), torch.tensor([[s]])
    )
    want = -0.5 * (math.log(2 * math.pi * s**2) + ((mu - m) ** 2 + t**2) / s**2)
    assert float(got) == pytest.approx(want, rel=1e-14)


def test_expected_log_density_against_monte_carlo(generator):
    d, n = 3, 200_000
    Sq, Sp = _spd(generator, d), _spd(generator, d)
    mq, mp = torch.randn(d, generator=generator), torch.randn(d, generator=generator)
    Lq, Lp = torch.linalg.cholesky(Sq), torch.linalg.cholesky(Sp)
    got = float(G.expected_log_density(mq, Lq, mp, Lp))
    x = mq + torch.randn(n, d, generator=generator) @ Lq.T
    samples = MultivariateNormal(mp, Sp).log_prob(x)
    se = float(samples.std()) / math.sqrt(n)
    assert abs(got - float(samples.mean())) < 5 * se
    # E_q[log q] = -H(q)
    torch.testing.assert_close(G.expected_log_density(mq, Lq, mq, Lq), -G.entropy(Lq))


def test_kl_divergence_matches_torch_batched(generator):
    Sq, Sp = _spd(generator, 4, 3), _spd(generator, 3)  # p broadcasts against 4 q's
    mq, mp = torch.randn(4, 3, generator=generator), torch.randn(3, generator=generator)
    Lq, Lp = torch.linalg.cholesky(Sq), torch.linalg.cholesky(Sp)
    got = G.kl_divergence(mq, Lq, mp, Lp)
    ref = kl_divergence(MultivariateNormal(mq, Sq), MultivariateNormal(mp, Sp))
    # 3 x 3 solves and log-determinants of condition number < ~20: ~1e-14 of terms of size ~1
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    # KL = -E_q[log p] - H(q); KL(q || q) = 0
    torch.testing.assert_close(got, -G.expected_log_density(mq, Lq, mp, Lp) - G.entropy(Lq))
    # zero up to the rounding of terms of size ~1 (d = 3): ~1e-15
    torch.testing.assert_close(G.kl_divergence(mq, Lq, mq, Lq), torch.zeros(4), atol=1e-13, rtol=0)
    with pytest.raises(ValueError, match="q_scale_tril"):
        G.kl_divergence(mq, Lq[..., :2, :2], mp, Lp)


def _dense_joint(gen: torch.Generator, dx: int, dy: int):
    J = _spd(gen, dx + dy)
    return J[:dx, :dx], J[:dx, dx:], J[dx:, dx:]


def test_conditional_matches_dense_formula(generator):
    dx, dy = 3, 2
    Sx, C, Sy = _dense_joint(generator, dx, dy)
    mx, my = torch.randn(dx, generator=generator), torch.randn(dy, generator=generator)
    y = torch.randn(dy, generator=generator)
    gain_t, cov = G.conditional(Sx, C, torch.linalg.cholesky(Sy))
    mean = mx + ((y - my)[None, :] @ gain_t)[0]
    Sxn, Cn, Syn = Sx.numpy(), C.numpy(), Sy.numpy()
    K = Cn @ np.linalg.inv(Syn)
    # a 2 x 2 inverse of condition number < ~20 against a Cholesky solve: ~1e-14 relative;
    # a covariance entry near zero carries the rounding of the whole matrix (atol)
    np.testing.assert_allclose(gain_t.numpy(), K.T, rtol=1e-10)
    np.testing.assert_allclose(mean.numpy(), mx.numpy() + K @ (y - my).numpy(), rtol=1e-10)
    np.testing.assert_allclose(cov.numpy(), Sxn - K @ Cn.T, rtol=1e-10, atol=1e-13)
    assert torch.equal(cov, cov.mT)
    with pytest.raises(ValueError, match="cross must have shape"):
        G.conditional(Sx, C.mT, torch.linalg.cholesky(Sy))


def test_rts_step_is_the_linear_gaussian_marginal(generator):
    dx, dy = 3, 2
    S, C, Sy = _dense_joint(generator, dx, dy)
    m, my = torch.randn(dx, generator=generator), torch.randn(dy, generator=generator)
    m2, S2 = torch.randn(dy, generator=generator), _spd(generator, dy)
    mean, cov, cross = G.rts_step(m, S, my, Sy, C, m2, S2)
    # oracle: x = A y + b + e, e ~ N(0, Q) (the conditional of the joint), y ~ N(m2, S2)
    A = C.numpy() @ np.linalg.inv(Sy.numpy())
    Q = S.numpy() - A @ C.numpy().T
    b = m.numpy() - A @ my.numpy()
    np.testing.assert_allclose(mean.numpy(), A @ m2.numpy() + b, rtol=1e-10)
    np.testing.assert_allclose(cov.numpy(), A @ S2.numpy() @ A.T + Q, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(cross.numpy(), A @ S2.numpy(), rtol=1e-10, atol=1e-13)
    # the unchanged marginal gives the joint back
    same = G.rts_step(m, S, my, Sy, C, my, Sy)
    for a, b_ in zip(same, (m, S, C), strict=True):
        torch.testing.assert_close(a, b_)
    with pytest.raises(CholeskyError, match="my prediction"):
        G.rts_step(m, S, my, -torch.eye(dy), C, m2, S2, name="my prediction")


def test_condition_gaussian_matches_dense_reference_per_row(generator):
    n = 5
    cov = _spd(generator, 3, n)
    mean = torch.randn(3, n, generator=generator)
    values = torch.randn(3, n, generator=generator)
    obs = torch.tensor([[1, 0, 0, 1, 0], [1, 1, 1, 1, 1], [0, 0, 0, 0, 0]], dtype=torch.bool)
    cm, cS = G.condition_gaussian(mean, cov, obs, values)
    o, u = obs[0].numpy(), ~obs[0].numpy()
    C, m, v = cov[0].numpy(), mean[0].numpy(), values[0].numpy()
    gain = C[np.ix_(u, o)] @ np.linalg.inv(C[np.ix_(o, o)])
    np.testing.assert_allclose(cm[0].numpy()[u], m[u] + gain @ (v[o] - m[o]), rtol=1e-10)
    np.testing.assert_allclose(cm[0].numpy()[o], v[o])
    ref = C[np.ix_(u, u)] - gain @ C[np.ix_(o, u)]
    np.testing.assert_allclose(cS[0].numpy()[np.ix_(u, u)], ref, rtol=1e-10, atol=1e-13)
    assert np.abs(cS[0].numpy()[o]).max() == 0
    # all observed: the values, no uncertainty; none observed: the prior unchanged
    torch.testing.assert_close(cm[1], values[1], rtol=0, atol=0)
    assert float(cS[1].abs().max()) == 0.0
    torch.testing.assert_close(cm[2], mean[2])
    torch.testing.assert_close(cS[2], cov[2])
    # the public name of the inference package is this function
    assert inference.condition_gaussian is G.condition_gaussian
    with pytest.raises(TypeError, match="observed must be a bool tensor"):
        G.condition_gaussian(mean, cov, obs.double(), values)
    with pytest.raises(ValueError, match="values must have shape"):
        G.condition_gaussian(mean, cov, obs, values[:, :2])


def test_condition_gaussian_shared_observed_set_matches_dense_reference(generator):
    """A batch that observes the same entries (the gathered-block path) against numpy."""
    n = 6
    cov = _spd(generator, 4, n)
    mean = torch.randn(4, n, generator=generator)
    values = torch.randn(4, n, generator=generator)
    obs = torch.tensor([1, 1, 0, 1, 0, 1], dtype=torch.bool).expand(4, n)
    cm, cS = G.condition_gaussian(mean, cov, obs, values)
    o, u = obs[0].numpy(), ~obs[0].numpy()
    for b in range(4):
        C, m, v = cov[b].numpy(), mean[b].numpy(), values[b].numpy()
        gain = C[np.ix_(u, o)] @ np.linalg.inv(C[np.ix_(o, o)])
        # float64 solves of a 4 x 4 SPD block with condition number O(10) on unit-scale
        # entries: 1e-10 relative, 1e-12 absolute for entries that cancel to near 0
        want = m[u] + gain @ (v[o] - m[o])
        np.testing.assert_allclose(cm[b].numpy()[u], want, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(cm[b].numpy()[o], v[o], rtol=0, atol=0)
        ref = C[np.ix_(u, u)] - gain @ C[np.ix_(o, u)]
        np.testing.assert_allclose(cS[b].numpy()[np.ix_(u, u)], ref, rtol=1e-10, atol=1e-12)
        assert np.abs(cS[b].numpy()[o]).max() == 0 and np.abs(cS[b].numpy()[:, o]).max() == 0


@pytest.mark.parametrize("with_covs", [True, False])
@pytest.mark.parametrize("batch_last", [False, True])
def test_mixture_moments_brute_force(generator, with_covs, batch_last):
    """Against explicit sums; ``batch_last``: weights and means stored with the batch innermost
    (``[K, B]``, ``[K, D, B]``, as the planner's particles), the branch that sums over them."""
    B, K, D, Du = 2, 4, 3, 2
    w = torch.softmax(torch.randn(B, K, generator=generator), -1)
    means = torch.randn(B, K, D, generator=generator)
    if batch_last:
        w, means = w.T.contiguous().T, means.permute(1, 2, 0).contiguous().permute(2, 0, 1)
        assert means.stride(0) == 1 and w.stride(0) == 1
        # weights shared by the batch ([K], [1, K]; K == D, so a misaligned broadcast would
        # not raise) and one batch member stored the same way: the product's results
        wk = torch.softmax(torch.randn(D, generator=generator), -1)
        mk = torch.randn(D, D, B, generator=generator).permute(2, 0, 1)
        pairs = [(wb, mk, wb, mk.contiguous()) for wb in (wk, wk[None])]
        pairs.append((w[:1], means[:1], w[:1].contiguous(), means[:1].contiguous()))
        for wa, ma, wb, mb in pairs:
            got, want = G.mixture_moments(wa, ma), G.mixture_moments(wb, mb)
            for a, b in zip(got, want, strict=True):
                torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
    covs = _spd(generator, B, K, D) if with_covs else None
    cross = torch.randn(B, K, Du, D, generator=generator)
    mean, cov, cr = G.mixture_moments(w, means, covs, cross)
    for b in range(B):
        wb, mb = w[b].numpy(), means[b].numpy()
        m_ref = sum(wb[k] * mb[k] for k in range(K))
        second = sum(
            wb[k] * ((covs[b, k].numpy() if with_covs else 0.0) + np.outer(mb[k], mb[k]))
            for k in range(K)
        )
        # sums of K = 4 terms of size ~1 in another order: ~4 eps, relative to the terms (atol)
        np.testing.assert_allclose(mean[b].numpy(), m_ref, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(cov[b].numpy(), second - np.outer(m_ref, m_ref), atol=1e-12)
        cr_ref = sum(wb[k] * cross[b, k].numpy() for k in range(K))
        np.testing.assert_allclose(cr[b].numpy(), cr_ref, rtol=1e-12, atol=1e-14)
    assert torch.equal(cov, cov.mT)
    # shared components [K, D] broadcast against the weights' batch
    m2, c2 = G.mixture_moments(w, means[0], None if covs is None else covs[0])
    m0, c0 = G.mixture_moments(w[0], means[0], None if covs is None else covs[0])
    torch.testing.assert_close(m2[0], m0)
    torch.testing.assert_close(c2[0], c0)


def test_mixture_moments_of_a_discrete_distribution():
    # two point masses: mean 0.7, variance 0.3 * 0.7 * (1 - 0)^2
    m, v = G.mixture_moments(torch.tensor([0.3, 0.7]), torch.tensor([[0.0], [1.0]]))
    torch.testing.assert_close(m, torch.tensor([0.7]))
    torch.testing.assert_close(v, torch.tensor([[0.21]]))


def test_mixture_moments_rejects_bad_shapes():
    w = torch.full((2, 3), 1 / 3)
    with pytest.raises(ValueError, match="means must have shape"):
        G.mixture_moments(w, torch.zeros(2, 4, 2))
    with pytest.raises(ValueError, match="covs must have shape"):
        G.mixture_moments(w, torch.zeros(2, 3, 2), torch.zeros(2, 3, 2, 3))
    with pytest.raises(ValueError, match="cross must have shape"):
        G.mixture_moments(w, torch.zeros(2, 3, 2), None, torch.zeros(2, 3, 2, 3))
    with pytest.raises(TypeError, match="weights must be a torch.Tensor"):
        G.mixture_moments([0.5, 0.5], torch.zeros(2, 1))


def test_batch_members_do_not_depend_on_each_other(generator):
    """Changing one batch member leaves the others' results unchanged bit for bit."""
    B, K, D = 6, 3, 3
    w = torch.softmax(torch.randn(B, K, generator=generator), -1)
    means, covs = torch.randn(B, K, D, generator=generator), _spd(generator, B, K, D)
    S = _spd(generator, B, D)
    L, mean = torch.linalg.cholesky(S), torch.randn(B, D, generator=generator)
    x = torch.randn(B, D, generator=generator)
    Sx, C, Sy = (t.expand(B, -1, -1).clone() for t in _dense_joint(generator, D, 2))

    def run(w, means, covs, L, x, Sy):
        out = [*G.mixture_moments(w, means, covs), G.log_density(x, mean, L)]
        out += [G.entropy(L), G.expected_log_density(x, L, mean, L), G.kl_divergence(x, L, mean, L)]
        out += list(G.conditional(Sx, C, torch.linalg.cholesky(Sy)))
        return out

    ref = run(w, means, covs, L, x, Sy)
    w2, means2, covs2, x2 = w.clone(), means.clone(), covs.clone(), x.clone()
    w2[3] = w2[3].flip(-1)
    means2[3] += 10.0
    covs2[3] *= 7.0
    x2[3] -= 3.0
    L2, Sy2 = L.clone(), Sy.clone()
    L2[3] *= 2.0
    Sy2[3] *= 3.0
    got = run(w2, means2, covs2, L2, x2, Sy2)
    keep = [0, 1, 2, 4, 5]
    for a, b in zip(got, ref, strict=True):
        assert torch.equal(a[keep], b[keep])


def test_independent_joint_is_block_diagonal_with_broadcasting(generator):
    Sa, Sb = _spd(generator, 2, 3), _spd(generator, 2)
    ma, mb = torch.randn(2, 3, generator=generator), torch.randn(4, 1, 2, generator=generator)
    mean, cov = G.independent_joint(ma, Sa, mb, Sb)  # batch [4, 2]
    assert mean.shape == (4, 2, 5) and cov.shape == (4, 2, 5, 5)
    for i in range(4):
        for j in range(2):
            torch.testing.assert_close(mean[i, j], torch.cat([ma[j], mb[i, 0]]), rtol=0, atol=0)
            torch.testing.assert_close(cov[i, j], torch.block_diag(Sa[j], Sb), rtol=0, atol=0)
    with pytest.raises(ValueError, match="mean_b must have shape"):
        G.independent_joint(ma, Sa, mb[..., :1], Sb)
