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
