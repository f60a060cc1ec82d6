"""The toolkit's kernels against gpytorch's generic kernel tests, and the gpytorch-style model API.

Every ``gpytorch.kernels.Kernel`` subclass of :mod:`hgpdm_torch.kernels` runs gpytorch's own
``BaseKernelTestCase`` (batches, active dims, indexing, pickling, dtype). Where a generic check
cannot apply as written, the override below says why and runs the same check on valid inputs.

The second half tests the constructor arguments of the models: a gpytorch ``Kernel`` as the
measurement kernel and the ``priors`` of Eq. 6.
"""

from __future__ import annotations

import math
import unittest

import gpytorch
import pytest
import torch
from gpytorch.priors import GammaPrior, NormalPrior
from gpytorch.test.base_kernel_test_case import BaseKernelTestCase

from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.kernels import (
    DenseLinearKernel,
    DiscreteIntentionKernel,
    IntentionRBFKernel,
    measurement_kernel,
)
from hgpdm_torch.models import GPDM, HGPDM, IDDM, ModelFileError, load_model

# ------------------------------------------------------------------------ generic kernel tests


class TestDenseLinearKernel(unittest.TestCase, BaseKernelTestCase):
    """A ``LinearKernel`` with a dense result: every generic test applies unchanged."""

    seed = 0

    def create_kernel_no_ard(self, **kwargs):
        return DenseLinearKernel(**kwargs)

    def create_kernel_ard(self, num_dims, **kwargs):
        return DenseLinearKernel(ard_num_dims=num_dims, **kwargs)

    def test_equals_gpytorch_linear_kernel_in_batch(self):
        kernel = DenseLinearKernel(ard_num_dims=2, batch_shape=torch.Size([3, 2]))
        with torch.no_grad():
            kernel.raw_variance.normal_()
        ref = gpytorch.kernels.LinearKernel(ard_num_dims=2, batch_shape=torch.Size([3, 2]))
        ref.raw_variance = kernel.raw_variance
        x = self.create_data_double_batch()
        self.assertAllClose(kernel(x).to_dense(), ref(x).to_dense())
        self.assertAllClose(kernel(x, diag=True), ref(x, diag=True))


class TestIntentionRBFKernel(unittest.TestCase, BaseKernelTestCase):
    """``exp(-|x - x'|^2 / 2 l_x^2 - |g - g'|^2 / 2 l_g^2)`` over ``[x, g]``, 2 + 2 columns.

    The kernel's input width ``x_dim + g_dim`` is fixed when it is built, unlike gpytorch's RBF,
    which takes any width. The generic data therefore get 4 columns (instead of 2 for the batched
    cases); ``active_dims=[0, 2, 4, 6]`` selects 4 columns as it is. It is not an ARD kernel (one
    length scale per block), so the ARD tests do not apply (``create_kernel_ard`` is not
    implemented, which the base class treats as "skip").
    """

    seed = 0
    x_dim, g_dim = 2, 2

    def create_kernel_no_ard(self, **kwargs):
        kernel = IntentionRBFKernel(self.x_dim, self.g_dim, **kwargs)
        kernel.lengthscale_x, kernel.lengthscale_g = 0.8, 1.7
        return kernel

    def create_data_single_batch(self):
        return torch.randn(2, 3, self.x_dim + self.g_dim)

    def create_data_double_batch(self):
        return torch.randn(3, 2, 50, self.x_dim + self.g_dim)

    def test_active_dims_range(self):
        # The generic test selects range(3, 9), six columns, for a kernel that takes any width;
        # this kernel takes x_dim + g_dim = 4, so the same check runs on range(3, 7).
        active_dims = list(range(3, 7))
        kernel = self.create_kernel_no_ard(active_dims=active_dims)
        x = self.create_data_no_batch()
        self.assertAllClose(
            kernel(x).to_dense(), self.create_kernel_no_ard()(x[:, active_dims]).to_dense()
        )

    def test_matches_ard_rbf_in_batch(self):
        kernel = self.create_kernel_no_ard(batch_shape=torch.Size([3, 2]))
        with torch.no_grad():
            kernel.raw_lengthscale_x.normal_()
            kernel.raw_lengthscale_g.normal_()
        ard = gpytorch.kernels.RBFKernel(ard_num_dims=4, batch_shape=torch.Size([3, 2]))
        ard.lengthscale = kernel.lengthscale_vector()
        x = self.create_data_double_batch()
        self.assertAllClose(kernel(x).to_dense(), ard(x).to_dense())
        self.assertAllClose(kernel(x, diag=True), ard(x, diag=True))

    def test_prior_kernel_pickles_and_samples(self):
        import pickle

        kernel = IntentionRBFKernel(
            2, 1, lengthscale_x_prior=GammaPrior(3.0, 2.0), lengthscale_g_prior=GammaPrior(2.0, 1.0)
        )
        kernel.sample_from_prior("lengthscale_g_prior")  # the setting closure works
        copy = pickle.loads(pickle.dumps(kernel))
        self.assertEqual(copy.lengthscale_g, kernel.lengthscale_g)
        for (name, _, prior, closure, _), (name2, module2, prior2, closure2, _) in zip(
            kernel.named_priors(), copy.named_priors(), strict=True
        ):
            self.assertEqual(name, name2)
            self.assertEqual(prior.log_prob(closure(kernel)), prior2.log_prob(closure2(module2)))


class TestDiscreteIntentionKernel(unittest.TestCase, BaseKernelTestCase):
    """``delta(g, g') k(x, x')`` with the integer code of g in the last input column.

    The kernel refuses a last column that is not a code in ``0 .. K-1`` (a real value would
    silently match nothing), so gpytorch's random real data cannot be its input. The data
    methods below keep gpytorch's shapes but put codes where the kernel reads them: the last
    column of the batched data, and columns 6 and 8 of the ``[50, 10]`` data, which are the last
    columns that ``active_dims=[0, 2, 4, 6]`` and ``range(3, 9)`` select (column 6 is then an
    ordinary input to ``k(x, x')``). With these inputs every generic test applies unchanged.
    """

    seed = 0
    num_values = 3

    def create_kernel_no_ard(self, **kwargs):
        base = gpytorch.kernels.RBFKernel(batch_shape=kwargs.get("batch_shape", torch.Size([])))
        base.lengthscale = 1.3
        return DiscreteIntentionKernel(base, self.num_values, **kwargs)

    def _codes(self, *shape):
        return torch.randint(0, self.num_values, shape).to(torch.get_default_dtype())

    def create_data_no_batch(self):
        x = torch.randn(50, 10)
        x[:, 6], x[:, 8] = self._codes(50), self._codes(50)
        return x

    def create_data_single_batch(self):
        return torch.cat([torch.randn(2, 3, 1), self._codes(2, 3, 1)], dim=-1)

    def create_data_double_batch(self):
        return torch.cat([torch.randn(3, 2, 50, 1), self._codes(3, 2, 50, 1)], dim=-1)

    def test_gram_is_base_times_code_match(self):
        kernel = self.create_kernel_no_ard()
        x = self.create_data_double_batch()
        same = (x[..., :, -1:] == x[..., :, -1:].transpose(-1, -2)).to(x.dtype)
        want = kernel.base_kernel(x[..., :-1]).to_dense() * same
        self.assertAllClose(kernel(x).to_dense(), want)


# ------------------------------------------------------------------------ model arguments


@pytest.fixture(scope="module")
def styles():
    return styled_movements(2, 2, 12, 5, seed=0)


def _prior_terms(model: GPDM) -> dict[str, torch.Tensor]:
    return {
        name: prior.log_prob(closure(module)).sum()
        for name, module, prior, closure, _ in model.named_priors()
    }


def test_default_priors_argument_is_bit_identical(styles):
    default = HGPDM(styles.sequences, styles.labels, 2, learn_noise=True)
    explicit = HGPDM(
        styles.sequences, styles.labels, 2, learn_noise=True, priors=GPDM.default_priors()
    )
    assert torch.equal(default.loss(), explicit.loss())
    assert list(default.state_dict()) == list(explicit.state_dict())


def test_priors_replace_and_remove_the_defaults(styles):
    default = GPDM(styles.sequences, 2, learn_noise=True)
    noise_prior = NormalPrior(math.log(0.05), 0.5)
    model = GPDM(
        styles.sequences,
        2,
        learn_noise=True,
        priors={"scales": None, "measurement_noise": noise_prior},
    )
    names = {name for name, *_ in model.named_priors()}
    assert names == {"measurement_kernel.beta1_prior", "measurement_noise_prior",
                     "transition_noise_prior"}  # fmt: skip
    assert model.measurement_noise_prior is noise_prior
    terms, ref = _prior_terms(model), _prior_terms(default)
    want_noise = noise_prior.log_prob(default.measurement_noise.log())
    torch.testing.assert_close(terms["measurement_noise_prior"], want_noise)
    # the loss changes by exactly the replaced and removed prior terms
    diff = model.loss() - default.loss()
    want = (ref["scales_prior"] + ref["measurement_noise_prior"]) - want_noise
    torch.testing.assert_close(diff, want)


def test_user_measurement_kernel_is_used_with_its_prior(styles):
    prior = GammaPrior(2.0, 2.0)
    kernel = gpytorch.kernels.ScaleKernel(
        gpytorch.kernels.RBFKernel(ard_num_dims=2, lengthscale_prior=prior)
    )
    model = HGPDM(styles.sequences, styles.labels, 2, measurement=kernel)
    assert model.measurement_kernel is kernel and model.measurement == "custom"
    assert "measurement_kernel.base_kernel.lengthscale_prior" in _prior_terms(model)
    assert any(p is kernel.base_kernel.raw_lengthscale for p in model.parameters())
    # Eq. 4 with the user's kernel: rebuild it by hand
    x = model.latent.detach()
    k = kernel(x).to_dense() + model.measurement_noise * torch.eye(x.shape[0])
    y = (model.observations - model.obs_mean) * model.scales
    dist = torch.distributions.MultivariateNormal(torch.zeros(x.shape[0]), k)
    want = -dist.log_prob(y.T).sum() - x.shape[0] * model.scales.log().sum()
    torch.testing.assert_close(model.measurement_nll(), want)
    before = kernel.base_kernel.lengthscale.detach().clone()
    model.fit(3, warn=False)
    assert not torch.equal(kernel.base_kernel.lengthscale, before)  # learned with the rest


def test_named_kernel_equals_the_same_kernel_passed_in(styles):
    named = GPDM(styles.sequences, 2, priors={"beta1": None})
    passed = GPDM(styles.sequences, 2, measurement=measurement_kernel("rbf"))
    assert torch.equal(named.loss(), passed.loss())


def test_custom_models_save_and_load_into_a_model_built_alike(styles, tmp_path):
    """A custom kernel is saved with its parameters; the file names it, and the user's code
    builds the model with it again (plain priors, here removing one, are rebuilt by the file)."""

    def build() -> GPDM:
        return GPDM(styles.sequences, 2, measurement=gpytorch.kernels.RBFKernel())

    model = build()
    model.save(tmp_path / "m.pt")
    with pytest.raises(ModelFileError, match=r"measurement \(a RBFKernel\)"):
        load_model(tmp_path / "m.pt")
    assert torch.equal(load_model(tmp_path / "m.pt", model=build()).loss(), model.loss())
    model = IDDM(styles.sequences, styles.labels, 2, priors={"scales": None})
    model.save(tmp_path / "i.pt")
    assert torch.equal(load_model(tmp_path / "i.pt").loss(), model.loss())


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"measurement": 3}, TypeError, "measurement must be"),
        ({"measurement": gpytorch.kernels.RBFKernel}, TypeError, "measurement must be"),
        ({"priors": [NormalPrior(0.0, 1.0)]}, TypeError, "priors must be a dict"),
        ({"priors": {"beta": NormalPrior(0.0, 1.0)}}, ValueError, r"'beta'.*in priors"),
        ({"priors": {"scales": 1.0}}, TypeError, r"priors\['scales'\] must be a gpytorch Prior"),
        (
            {"measurement": "linear", "priors": {"beta1": NormalPrior(0.0, 1.0)}},
            ValueError,
            r"priors\['beta1'\] applies to measurement='rbf' only",
        ),
    ],
)
def test_bad_model_arguments_are_named(styles, kwargs, error, match):
    with pytest.raises(error, match=match):
        GPDM(styles.sequences, 2, **kwargs)


def test_bad_kernel_arguments_are_named():
    with pytest.raises(TypeError, match="lengthscale_g_prior must be a gpytorch Prior"):
        IntentionRBFKernel(2, 1, lengthscale_g_prior=1.0)
    with pytest.raises(TypeError, match="measurement kernel must be"):
        measurement_kernel(None)
