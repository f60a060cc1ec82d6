"""GPPosterior.predict against gpytorch's ExactGP with the same kernel and noise."""

from __future__ import annotations

import gpytorch
import pytest
import torch

from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.kernels import measurement_kernel, transition_kernel


class _ExactGP(gpytorch.models.ExactGP):
    def __init__(self, x, y, kernel, likelihood):
        super().__init__(x, y, likelihood)
        self.mean_module = gpytorch.means.ZeroMean()
        self.covar_module = kernel

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def _gpytorch_predict(kernel, x, y, noise, xs):
    lik = gpytorch.likelihoods.GaussianLikelihood()
    lik.noise = noise
    model = _ExactGP(x, y, kernel, lik).eval()
    lik.eval()
    with (
        torch.no_grad(),
        gpytorch.settings.fast_pred_var(False),
        gpytorch.settings.skip_posterior_variances(False),
    ):
        out = model(xs)
    return out.mean, out.variance


KERNELS = {
    "rbf": lambda: measurement_kernel("rbf", beta1=0.7),
    "linear": lambda: measurement_kernel("linear"),
    "gpdm": lambda: transition_kernel("gpdm", 3, alpha=(0.9, 0.5, 0.1, 1e-3)),
    "continuous": lambda: transition_kernel("continuous", 2, g_dim=1, alpha=(0.9, 0.5, 0.1, 1e-3)),
    "iddm_continuous": lambda: transition_kernel("iddm_continuous", 2, g_dim=1),
}


@pytest.mark.parametrize("name", KERNELS)
def test_predict_matches_gpytorch_exact_gp(name, generator):
    x = torch.randn(30, 3, generator=generator)
    y = torch.sin(x).sum(-1) + 0.1 * torch.randn(30, generator=generator)
    xs = torch.randn(7, 3, generator=generator)
    kernel = KERNELS[name]()
    post = GPPosterior(kernel, x, y[:, None], 0.05)
    mean, var = post.predict(xs)
    oracle_kernel = kernel
    if name == "linear":  # gpytorch's own LinearKernel as the reference for our dense variant
        oracle_kernel = gpytorch.kernels.LinearKernel()
        oracle_kernel.variance = 1.0
    ref_mean, ref_var = _gpytorch_predict(oracle_kernel, x, y, 0.05, xs)
    torch.testing.assert_close(mean[:, 0], ref_mean, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(var[:, 0], ref_var, rtol=1e-7, atol=1e-8)


def test_predict_scale_offset_multi_output_and_batch(generator):
    x = torch.randn(20, 2, generator=generator)
    y = torch.randn(20, 3, generator=generator)
    scale, offset = torch.tensor([1.0, 2.0, 0.5]), torch.tensor([0.1, -1.0, 3.0])
    post = GPPosterior(measurement_kernel("rbf"), x, y, 0.1, scale=scale, offset=offset)
    xs = torch.randn(4, 5, 2, generator=generator)
    mean, var = post.predict(xs)
    assert mean.shape == var.shape == (4, 5, 3)
    for d in range(3):
        ref_mean, ref_var = _gpytorch_predict(post.kernel, x, y[:, d], 0.1, xs.reshape(-1, 2))
        torch.testing.assert_close(mean[..., d].reshape(-1), ref_mean + offset[d])
        torch.testing.assert_close(var[..., d].reshape(-1), ref_var * scale[d] ** 2)
    _, noisy = post.predict(xs, include_noise=True)
    torch.testing.assert_close(noisy - var, 0.1 * scale.pow(2).expand_as(var))


def test_discrete_kernel_isolates_intentions(generator):
    x = torch.randn(40, 2, generator=generator)
    codes = torch.arange(40) % 2
    y = torch.where(codes == 0, x[:, 0], -x[:, 0])[:, None]
    kernel = transition_kernel("discrete", 2, num_values=2, alpha=(0.9, 0.5, 0.1, 1e-3))
    post = GPPosterior(kernel, torch.cat([x, codes[:, None].double()], -1), y, 1e-3)
    xs = torch.randn(5, 2, generator=generator)
    m0, _ = post.predict(torch.cat([xs, torch.zeros(5, 1)], -1))
    # A GP trained on code-0 points alone gives the same prediction: other codes do not leak in.
    own = GPPosterior(kernel.base_kernel, x[codes == 0], y[codes == 0], 1e-3)
    torch.testing.assert_close(m0, own.predict(xs)[0])


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"train_inputs": torch.randn(3, 2), "train_targets": torch.randn(4, 1)}, "same N"),
        ({"train_inputs": torch.randn(3, 2), "train_targets": torch.randn(3)}, "train_targets"),
        ({"noise": 0.0}, "noise"),
        ({"train_inputs": torch.tensor([[float("nan"), 1.0]])}, "train_inputs"),
    ],
)
def test_bad_inputs_raise(kwargs, match):
    args = {"train_inputs": torch.randn(3, 2), "train_targets": torch.randn(3, 1), "noise": 0.1}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        GPPosterior(measurement_kernel("rbf"), **args)


def test_predict_rejects_wrong_dims():
    post = GPPosterior(measurement_kernel("rbf"), torch.randn(5, 2), torch.randn(5, 1), 0.1)
    with pytest.raises(ValueError, match="x"):
        post.predict(torch.randn(4, 3))
    with pytest.raises(TypeError, match="kernel"):
        GPPosterior("rbf", torch.randn(5, 2), torch.randn(5, 1), 0.1)


def test_posterior_is_a_frozen_snapshot(generator):
    kernel = transition_kernel("gpdm", 2, alpha=(0.9, 0.5, 0.1, 1e-3))
    x, y = torch.randn(15, 2, generator=generator), torch.randn(15, 2, generator=generator)
    post = GPPosterior(kernel, x, y, 0.01)
    xs = torch.randn(3, 2, generator=generator)
    before = post.predict(xs)
    kernel.kernels[0].outputscale = 5.0  # e.g. the model is fitted further
    torch.testing.assert_close(post.predict(xs), before, rtol=0, atol=0)
    mean, _, _ = post.predict_gaussian(xs, torch.zeros(3, 2, 2))
    torch.testing.assert_close(mean, before[0])


def test_undetached_posterior_supports_repeated_backward(generator):
    kernel = measurement_kernel("rbf")
    x, y = torch.randn(10, 2, generator=generator), torch.randn(10, 1, generator=generator)
    post = GPPosterior(kernel, x, y, 0.1, detach=False)
    for _ in range(2):
        kernel.zero_grad()
        mean, cov, _ = post.predict_gaussian(torch.zeros(2), 0.1 * torch.eye(2))
        (mean.sum() + cov.sum()).backward()
        assert kernel.raw_lengthscale.grad is not None


def test_moment_matched_covariance_stays_psd_for_a_nearly_exact_gp(generator):
    # alpha-bar's very smooth RBF and tiny noise: K is ill-conditioned and beta^T psi2 beta and
    # mean mean^T cancel to rounding error, which used to leave negative variances.
    t = torch.linspace(0, 6, 300)
    x = torch.stack([t.sin(), t.cos()], -1) + 0.01 * torch.randn(300, 2, generator=generator)
    post = GPPosterior(transition_kernel("gpdm", 2), x, torch.roll(x, -1, 0), 1e-6)
    mu = torch.tensor([[0.5, 0.5], [2.0, 2.0]])
    _, cov, _ = post.predict_gaussian(mu, torch.zeros(2, 2, 2))
    assert torch.linalg.eigvalsh(cov).min() >= 0
    # The variance itself is only determined to ~cond(K) * eps here (signal variance ~1).
    _, var = post.predict(mu)
    torch.testing.assert_close(cov.diagonal(dim1=-2, dim2=-1), var, atol=1e-4, rtol=0)


def test_predict_is_differentiable_in_x(generator):
    post = GPPosterior(
        measurement_kernel("rbf"),
        torch.randn(8, 2, generator=generator),
        torch.randn(8, 1, generator=generator),
        0.1,
    )
    x = torch.randn(3, 2, generator=generator, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: post.predict(x), (x,))
    assert not any(p.requires_grad for p in post.kernel.parameters())
