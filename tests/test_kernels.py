"""Kernels of the H-GPDM/IDDM against explicit formulas, and their parameter handling."""

from __future__ import annotations

import gpytorch
import pytest
import torch

from hgpdm_torch.kernels import (
    ALPHA_BAR,
    DenseLinearKernel,
    DiscreteIntentionKernel,
    IntentionRBFKernel,
    intention_rbf,
    measurement_kernel,
    transition_kernel,
)


def test_intention_rbf_matches_formula_and_ard_equivalent(generator):
    k = IntentionRBFKernel(3, 2)
    k.lengthscale_x, k.lengthscale_g = 0.7, 1.9
    x1, x2 = torch.randn(4, 5, generator=generator), torch.randn(6, 5, generator=generator)
    dx = torch.cdist(x1[:, :3], x2[:, :3]) ** 2
    dg = torch.cdist(x1[:, 3:], x2[:, 3:]) ** 2
    want = torch.exp(-0.5 * dx / 0.7**2 - 0.5 * dg / 1.9**2)
    torch.testing.assert_close(k(x1, x2).to_dense(), want)
    ard = gpytorch.kernels.RBFKernel(ard_num_dims=5)
    ard.lengthscale = k.lengthscale_vector()
    torch.testing.assert_close(k(x1, x2).to_dense(), ard(x1, x2).to_dense())
    torch.testing.assert_close(k(x1, x1, diag=True), torch.ones(4))


def test_intention_rbf_prior_and_constraint():
    prior = gpytorch.priors.GammaPrior(2.0, 2.0)
    k = IntentionRBFKernel(2, 1, lengthscale_x_prior=prior)
    names = [name for name, *_ in k.named_priors()]
    assert names == ["lengthscale_x_prior"]
    with torch.no_grad():
        k.raw_lengthscale_x.fill_(-50.0)
    assert float(k.lengthscale_x) > 0


def test_discrete_kernel_is_block_diagonal(generator):
    base = measurement_kernel("rbf")
    k = DiscreteIntentionKernel(base, 3)
    x = torch.randn(6, 2, generator=generator)
    codes = torch.tensor([0.0, 1, 2, 0, 1, 2])[:, None]
    gram = k(torch.cat([x, codes], -1)).to_dense()
    same = codes == codes.T
    torch.testing.assert_close(gram, base(x).to_dense() * same)


@pytest.mark.parametrize("kind", ["discrete", "iddm_discrete"])
def test_shared_discrete_kernel_mixes_common_and_per_value_dynamics(kind, generator):
    x = torch.randn(7, 2, generator=generator)
    codes = torch.tensor([0.0, 1, 2, 0, 1, 2, 2])[:, None]
    xg = torch.cat([x, codes], -1)
    alpha = (0.8, 0.5, 0.3, 1e-3)
    block = transition_kernel(kind, 2, num_values=3, alpha=alpha)
    base = block.base_kernel(x).to_dense()  # k_0 at the thesis's alpha
    shared = transition_kernel(kind, 2, num_values=3, alpha=alpha, sharing=0.3)
    same = (codes == codes.T).double()
    want = 0.3 * base + 0.7 * same * base
    torch.testing.assert_close(shared(xg).to_dense(), want)
    torch.testing.assert_close(shared(xg, diag=True), want.diagonal())
    # sharing = 0 is the thesis's block kernel itself
    thesis = transition_kernel(kind, 2, num_values=3, sharing=0.0)
    assert isinstance(thesis, DiscreteIntentionKernel)


def test_dense_linear_kernel_equals_gpytorch_linear(generator):
    x1, x2 = torch.randn(5, 3, generator=generator), torch.randn(4, 3, generator=generator)
    ours, ref = DenseLinearKernel(ard_num_dims=3), gpytorch.kernels.LinearKernel(ard_num_dims=3)
    ours.variance = ref.variance = torch.tensor([[0.5, 1.0, 2.0]])
    torch.testing.assert_close(ours(x1, x2).to_dense(), ref(x1, x2).to_dense())
    torch.testing.assert_close(ours(x1, x1, diag=True), ref(x1, x1, diag=True))


def test_transition_kernel_hyperparameters_follow_the_thesis():
    k = transition_kernel("discrete", 3, num_values=2)
    scale, lin = k.base_kernel.kernels
    a1, a2, a3, _ = ALPHA_BAR
    assert float(scale.outputscale) == pytest.approx(a1)
    assert float(scale.base_kernel.lengthscale) ** -2 == pytest.approx(a2)
    assert float(lin.variance) == pytest.approx(a3)
    lin_m = measurement_kernel("linear")
    assert float(lin_m.variance) == 1.0 and not lin_m.raw_variance.requires_grad


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda: transition_kernel("quadratic", 2), "unknown transition kernel"),
        (lambda: measurement_kernel("matern"), "unknown measurement kernel"),
        (lambda: transition_kernel("discrete", 2), "num_values"),
        (lambda: transition_kernel("gpdm", 2, alpha=(1.0, 2.0)), "alpha"),
        (lambda: transition_kernel("gpdm", 2, alpha=(1.0, -2.0, 1.0, 1.0)), "positive"),
        (lambda: IntentionRBFKernel(0, 1), "x_dim"),
        (lambda: transition_kernel("gpdm", 2, alpha=(-1.0, 1.0, 1.0, 1.0)), "positive"),
        (lambda: transition_kernel("continuous", 2, alpha_g=(1.0,)), "alpha_g"),
        (lambda: transition_kernel("discrete", 2, num_values=2, sharing=1.0), r"\[0, 1\)"),
        (lambda: transition_kernel("discrete", 2, num_values=2, sharing=-0.1), "sharing"),
        (lambda: transition_kernel("gpdm", 2, sharing=0.5), "discrete kinds only"),
        (lambda: DiscreteIntentionKernel(measurement_kernel("rbf"), 0), "num_values"),
        (lambda: IntentionRBFKernel(2, 1)(torch.randn(3, 2)).to_dense(), "3 columns"),
    ],
)
def test_bad_kernel_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_discrete_kernel_rejects_non_kernel():
    with pytest.raises(TypeError, match="base_kernel"):
        DiscreteIntentionKernel("rbf", 2)


@pytest.mark.parametrize("code", [7.0, -1.0, 0.5])
def test_discrete_kernel_and_posterior_refuse_codes_outside_the_values(code):
    """A code that matches no value would give the prior silently (probe of issue 15)."""
    from hgpdm_torch.datasets import styled_movements
    from hgpdm_torch.models import IDDM

    data = styled_movements(2, 3, 10, 4, seed=0)
    post = IDDM(data.sequences, data.labels, 2, measurement="linear").transition_posterior()
    good = torch.tensor([[0.1, 0.2, 1.0]], dtype=torch.float64)
    mean, _ = post.predict(good)
    assert bool(mean.abs().sum() > 0)  # a valid code is predicted from its own block
    with pytest.raises(ValueError, match=r"codes g must be integers in \[0, 1\]"):
        post.predict(torch.tensor([[0.1, 0.2, code]], dtype=torch.float64))
    with pytest.raises(ValueError, match="codes g"):
        post.kernel(good, torch.tensor([[0.0, 0.0, code]], dtype=torch.float64)).to_dense()


def test_intention_rbf_product_equals_the_bespoke_kernel(generator, rbf_rounding):
    """gpytorch's RBF(x) * RBF(g) (a ProductKernel) is IntentionRBFKernel to an ulp."""
    old = IntentionRBFKernel(3, 2)
    old.lengthscale_x, old.lengthscale_g = 0.7, 1.9
    new = intention_rbf(3, 2, 0.7, 1.9)
    assert isinstance(new, gpytorch.kernels.ProductKernel)
    assert [type(k) for k in new.kernels] == [gpytorch.kernels.RBFKernel] * 2
    x1, x2 = torch.randn(40, 5, generator=generator), torch.randn(6, 5, generator=generator)
    ls = old.lengthscale_vector().detach()
    for a, b in ((x1, x2), (x1, x1)):
        # squared distances formed two ways (measured: up to 0.01 of the bound, ~1.5e-13)
        tol = rbf_rounding(a, b, ls)
        torch.testing.assert_close(new(a, b).to_dense(), old(a, b).to_dense(), rtol=0, atol=tol)
    # the diagonal is exp(0) = 1 both ways: exact
    torch.testing.assert_close(new(x1, diag=True), old(x1, diag=True), rtol=0, atol=0)
    with pytest.raises(ValueError, match="x_dim and g_dim"):
        intention_rbf(0, 1)


@pytest.mark.parametrize("kind", ["iddm_continuous", "continuous"])
def test_intention_rbf_loads_the_bespoke_kernels_state_dict(kind, generator, rbf_rounding):
    """A state dict holding IntentionRBFKernel entries (the transition kernel of a model saved
    before the switch to the product form) loads into today's transition kernel, nested at any
    prefix, with the same Gram matrix."""
    old = transition_kernel(kind, 2, g_dim=1, alpha=(0.8, 1.7, 0.3, 1e-3), alpha_g=(2.5, 0.4))
    old_scaled = old if kind == "iddm_continuous" else old.kernels[0]
    bespoke = IntentionRBFKernel(2, 1)
    bespoke.lengthscale_x, bespoke.lengthscale_g = (
        k.lengthscale for k in old_scaled.base_kernel.kernels
    )
    old_scaled.base_kernel = bespoke
    with torch.no_grad():
        for p in old.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=generator))
    new = transition_kernel(kind, 2, g_dim=1)
    scaled = new if kind == "iddm_continuous" else new.kernels[0]
    assert isinstance(scaled.base_kernel, gpytorch.kernels.ProductKernel)
    state = old.state_dict()
    assert any("raw_lengthscale_x" in key for key in state)
    missing, unexpected = new.load_state_dict(state)
    assert not missing and not unexpected
    x = torch.randn(9, 3, generator=generator)
    # the RBF part's squared distances formed two ways, times its output scale; the other
    # terms are the same code (measured: up to 0.02 of the bound)
    with torch.no_grad():
        tol = float(old_scaled.outputscale) * rbf_rounding(x, x, bespoke.lengthscale_vector())
    torch.testing.assert_close(new(x).to_dense(), old(x).to_dense(), rtol=0, atol=tol)
    lx, lg = (k.lengthscale for k in scaled.base_kernel.kernels)
    ref = old if kind == "iddm_continuous" else old.kernels[0]
    assert torch.equal(lx, ref.base_kernel.lengthscale_x)
    assert torch.equal(lg, ref.base_kernel.lengthscale_g)
    new.load_state_dict(new.state_dict())  # its own state dict still loads (no renaming)
