"""GPPosterior.predict_gaussian: point limit, Monte Carlo moments, batching, gradients, errors."""

from __future__ import annotations

import itertools

import pytest
import torch

from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.kernels import measurement_kernel, transition_kernel
from hgpdm_torch.linalg import shared_matmul

DX = 2
# "_shared": the discrete kernel with a share of common dynamics (not block-diagonal)
KINDS = ["gpdm", "continuous", "iddm_continuous", "discrete", "iddm_discrete", "discrete_shared"]


def make_posterior(kind: str, gen: torch.Generator, N: int = 25) -> GPPosterior:
    """A transition-style GP on ``[x, g]`` with nonlinear targets, output scale and offset."""
    kernel = transition_kernel(
        kind.removesuffix("_shared"),
        DX,
        g_dim=1,
        num_values=3,
        alpha=(0.9, 0.7, 0.2, 1e-2),
        alpha_g=(1.5, 0.3),
        sharing=0.4 if kind.endswith("_shared") else 0.0,
    )
    x = torch.randn(N, DX, generator=gen)
    if kind == "gpdm":
        inputs = x
    elif "discrete" in kind:
        inputs = torch.cat([x, torch.randint(0, 3, (N, 1), generator=gen).double()], -1)
    else:
        inputs = torch.cat([x, torch.randn(N, 1, generator=gen)], -1)
    y = torch.sin(2 * x) + 0.3 * inputs[:, -1:] + 0.05 * torch.randn(N, DX, generator=gen)
    return GPPosterior(
        kernel, inputs, y, 0.01, scale=torch.tensor([1.0, 1.7]), offset=torch.tensor([0.2, -0.4])
    )


def known_g(kind: str, gen: torch.Generator, shape=()) -> torch.Tensor | None:
    if kind == "gpdm":
        return None
    if "discrete" in kind:
        return torch.randint(0, 3, (*shape, 1), generator=gen).double()
    return torch.randn(*shape, 1, generator=gen)


def random_cov(D, gen, scale=0.3):
    A = torch.randn(D, D, generator=gen) * scale
    return A @ A.T + 0.02 * torch.eye(D)


@pytest.mark.parametrize("include_noise", [False, True])
@pytest.mark.parametrize("kind", KINDS)
def test_zero_covariance_equals_point_prediction(kind, include_noise, generator):
    gp = make_posterior(kind, generator)
    mu = torch.randn(5, DX, generator=generator)
    g = known_g(kind, generator, (5,))
    mean, cov, io = gp.predict_gaussian(
        mu, torch.zeros(5, DX, DX), g=g, include_noise=include_noise
    )
    x = mu if g is None else torch.cat([mu, g], -1)
    m, v = gp.predict(x, include_noise=include_noise)
    torch.testing.assert_close(mean, m, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(cov, torch.diag_embed(v), rtol=1e-9, atol=1e-12)
    assert torch.all(io == 0)


@pytest.mark.parametrize("kind", ["rbf", "linear"])
def test_measurement_kernels_zero_covariance(kind, generator):
    x = torch.randn(20, 3, generator=generator)
    z = torch.cat([x[:, :1] ** 2, x.sum(-1, keepdim=True)], -1)
    gp = GPPosterior(
        measurement_kernel(kind, beta1=0.5), x, z, 0.05, scale=torch.tensor([2.0, 0.5])
    )
    mu = torch.randn(4, 3, generator=generator)
    mean, cov, _ = gp.predict_gaussian(mu, torch.zeros(3, 3), include_noise=True)
    m, v = gp.predict(mu, include_noise=True)
    torch.testing.assert_close(mean, m)
    torch.testing.assert_close(cov, torch.diag_embed(v))


def mc_moments(gp, mu, Sigma, g, n, gen, chunk=100_000):
    """Monte Carlo moments via the law of total (co)variance, from point predictions only.

    Per sample ``x`` the vector ``[m(x), m(x) m(x)^T, var(x), x m(x)^T]`` is averaged; returns
    (mean, cov, Cov[x, f]) and their standard errors.
    """
    D, Do = mu.shape[-1], gp.output_dim
    L = torch.linalg.cholesky(Sigma)
    s1 = s2 = 0.0
    for _ in range(n // chunk):
        eps = torch.randn(chunk, D, generator=gen)
        x = mu + eps @ L.T
        inp = x if g is None else torch.cat([x, g.expand(chunk, g.shape[-1])], -1)
        m, v = gp.predict(inp)
        mc = m - gp.offset
        feats = torch.cat(
            [
                m,
                (mc[:, :, None] * mc[:, None, :]).reshape(chunk, -1),
                v,
                ((x - mu)[:, :, None] * m[:, None, :]).reshape(chunk, -1),
            ],
            -1,
        )
        s1, s2 = s1 + feats.sum(0), s2 + feats.pow(2).sum(0)
    avg = s1 / n
    se = ((s2 / n - avg.pow(2)).clamp_min(0) / n).sqrt()
    mean, se_mean = avg[:Do], se[:Do]
    m2 = avg[Do : Do + Do * Do].reshape(Do, Do)
    ev = avg[Do + Do * Do : 2 * Do + Do * Do]
    cov = m2 - (mean - gp.offset)[:, None] * (mean - gp.offset)[None, :] + torch.diag(ev)
    se_cov = se[Do : Do + Do * Do].reshape(Do, Do) + torch.diag(se[Do + Do * Do : 2 * Do + Do * Do])
    io = avg[2 * Do + Do * Do :].reshape(D, Do)
    se_io = se[2 * Do + Do * Do :].reshape(D, Do)
    return (mean, cov, io), (se_mean, se_cov, se_io)


def assert_within(actual, expected, se, k=5.0, slack=1e-9):
    z = (actual - expected).abs() / (k * se + slack)
    assert float(z.max()) < 1.0, f"{actual}\nvs MC {expected}\n(se {se})"


@pytest.mark.parametrize("kind", KINDS)
def test_moments_against_monte_carlo(kind, generator):
    gp = make_posterior(kind, generator)
    mu = 0.5 * torch.randn(DX, generator=generator)
    Sigma = random_cov(DX, generator)
    g = known_g(kind, generator)
    ours = gp.predict_gaussian(mu, Sigma, g=g)
    ref, se = mc_moments(gp, mu, Sigma, g, 400_000, generator)
    for a, r, s in zip(ours, ref, se, strict=True):
        assert_within(a, r, s)


def test_gaussian_intention_correlated_with_x(generator):
    """Uncertain continuous g, jointly Gaussian with x: the whole input is the Gaussian."""
    gp = make_posterior("continuous", generator)
    mu = torch.tensor([0.2, -0.3, 0.5])
    Sigma = random_cov(3, generator)
    assert abs(float(Sigma[0, 2])) > 0.01
    ours = gp.predict_gaussian(mu, Sigma)
    assert ours[2].shape == (3, DX)
    ref, se = mc_moments(gp, mu, Sigma, None, 400_000, generator)
    for a, r, s in zip(ours, ref, se, strict=True):
        assert_within(a, r, s)


@pytest.mark.parametrize("kind", ["continuous", "discrete", "iddm_continuous"])
def test_intentions_share_x_and_match_loop(kind, generator):
    """mu [B, 1, D] with g [B, K, Dg] equals one call per (stream, intention)."""
    gp = make_posterior(kind, generator)
    B, K = 3, 4
    mu = torch.randn(B, 1, DX, generator=generator)
    Sigma = torch.stack([random_cov(DX, generator) for _ in range(B)])[:, None]
    g = known_g(kind, generator, (B, K))
    mean, cov, io = gp.predict_gaussian(mu, Sigma, g=g, include_noise=True)
    assert mean.shape == (B, K, DX) and cov.shape == (B, K, DX, DX) and io.shape == (B, K, DX, DX)
    for b, k in itertools.product(range(B), range(K)):
        m1, c1, i1 = gp.predict_gaussian(mu[b, 0], Sigma[b, 0], g=g[b, k], include_noise=True)
        torch.testing.assert_close(mean[b, k], m1)
        torch.testing.assert_close(cov[b, k], c1)
        torch.testing.assert_close(io[b, k], i1)


def test_joint_cov_gives_cross_covariance_of_another_variable(generator):
    """Cov[s, f(x)] for s jointly Gaussian with x (Stein's lemma), checked by Monte Carlo."""
    gp = make_posterior("gpdm", generator)
    full = random_cov(3, generator, scale=0.5)  # [x (2), s (1)]
    mu = torch.tensor([0.1, 0.4, -1.0])
    _, _, io = gp.predict_gaussian(mu[:2], full[:2, :2], joint_cov=full[:, :2])
    assert io.shape == (3, DX)
    torch.testing.assert_close(io[:2], gp.predict_gaussian(mu[:2], full[:2, :2])[2])
    L = torch.linalg.cholesky(full)
    n = 400_000
    x = mu + torch.randn(n, 3, generator=generator) @ L.T
    m, _ = gp.predict(x[:, :2])
    prod = (x[:, 2:] - mu[2]) * m
    se = prod.std(0) / n**0.5
    assert_within(io[2], prod.mean(0), se)


def test_gradcheck_moments(generator):
    gp = make_posterior("continuous", generator, N=8)
    mu = torch.tensor([0.2, -0.1], requires_grad=True)
    A = torch.tensor([[0.4, 0.0], [0.1, 0.3]], requires_grad=True)
    g = torch.tensor([0.3], requires_grad=True)

    def f(mu, A, g):
        mean, cov, io = gp.predict_gaussian(mu, A @ A.T, g=g, include_noise=True)
        return mean, cov, io

    assert torch.autograd.gradcheck(f, (mu, A, g))


def test_hyperparameter_gradients_when_not_detached(generator):
    kernel = transition_kernel("gpdm", DX, alpha=(0.9, 0.7, 0.2, 1e-2))
    x = torch.randn(10, DX, generator=generator)
    gp = GPPosterior(kernel, x, torch.sin(x), 0.01, detach=False)
    mean, cov, _ = gp.predict_gaussian(torch.zeros(DX), 0.1 * torch.eye(DX))
    (mean.sum() + cov.sum()).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in kernel.parameters())
    detached = GPPosterior(kernel, x, torch.sin(x), 0.01)
    mean, cov, _ = detached.predict_gaussian(torch.zeros(DX), 0.1 * torch.eye(DX))
    assert not mean.requires_grad and not cov.requires_grad


def test_shared_matmul_matches_broadcast_matmul(generator):
    for sa, sb in [((3, 1), (3, 6)), ((1,), (7, 3)), ((2, 1), (1, 3)), ((), (4,)), ((5,), (5,))]:
        a = torch.randn(*sa, 4, 5, generator=generator)
        b = torch.randn(*sb, 5, 2, generator=generator)
        torch.testing.assert_close(shared_matmul(a, b), a @ b)


def test_bad_inputs_raise(generator):
    gp = make_posterior("continuous", generator)
    eye = torch.eye(DX)
    g = torch.tensor([0.1])
    with pytest.raises(ValueError, match="NaN"):
        gp.predict_gaussian(torch.tensor([float("nan"), 0.0]), eye, g=g)
    with pytest.raises(ValueError, match="positive semi-definite"):
        gp.predict_gaussian(torch.zeros(DX), -eye, g=g)
    with pytest.raises(ValueError, match="trailing shape"):
        gp.predict_gaussian(torch.zeros(DX), torch.eye(3), g=g)
    with pytest.raises(ValueError, match="input dim"):
        gp.predict_gaussian(torch.zeros(DX), eye)  # g missing
    with pytest.raises(ValueError, match="input dim"):
        gp.predict_gaussian(torch.zeros(DX), eye, g=torch.zeros(2))
    with pytest.raises(ValueError, match="joint_cov"):
        gp.predict_gaussian(torch.zeros(DX), eye, g=g, joint_cov=torch.zeros(3, 3))


def test_discrete_blocks_equal_generic_masking(generator):
    """The per-code block path equals the generic path (delta factors over all N points)."""
    from gpytorch.kernels import AdditiveKernel

    gp = make_posterior("discrete", generator)
    # wrapping the kernel hides it from the block path but leaves the function unchanged
    generic = GPPosterior(
        AdditiveKernel(gp.kernel),
        gp.train_inputs,
        gp.train_targets,
        gp.noise,
        scale=gp.scale,
        offset=gp.offset,
    )
    assert gp.blocks() is not None and generic.blocks() is None
    mu = torch.randn(2, 1, DX, generator=generator)
    Sigma = torch.stack([random_cov(DX, generator) for _ in range(2)])[:, None]
    g = torch.tensor([0.0, 1.0, 2.0])[None, :, None]
    for a, b in zip(
        gp.predict_gaussian(mu, Sigma, g=g), generic.predict_gaussian(mu, Sigma, g=g), strict=True
    ):
        torch.testing.assert_close(a, b)


def test_discrete_code_without_points_and_bad_codes(generator):
    gp = make_posterior("iddm_discrete", generator)
    keep = gp.train_inputs[:, -1] != 2  # code 2 gets no training points
    gp = GPPosterior(gp.kernel, gp.train_inputs[keep], gp.train_targets[keep], gp.noise)
    mean, cov, io = gp.predict_gaussian(torch.zeros(DX), 0.1 * torch.eye(DX), g=torch.tensor([2.0]))
    torch.testing.assert_close(mean, torch.zeros(DX))  # prior mean
    torch.testing.assert_close(cov, 0.9 * torch.eye(DX))  # prior variance alpha_1
    for bad in (torch.tensor([1.5]), torch.tensor([3.0]), torch.tensor([-1.0])):
        with pytest.raises(ValueError, match="codes"):
            gp.predict_gaussian(torch.zeros(DX), torch.eye(DX), g=bad)
