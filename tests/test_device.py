"""Device and dtype plumbing (issue 17): every tensor the library creates takes its device and
dtype from the model or the inputs.

Two oracles:

- *No tensor on the default device.* With torch's default device set to ``"meta"`` (and,
  separately, the default dtype to float32) while the models and inputs are float64 on the CPU,
  a tensor created without an explicit ``device=`` lands on ``meta`` and mixing it with a CPU
  tensor raises; one created without ``dtype=`` is float32. Every result must equal, bit for
  bit, the run with the usual defaults. This catches on a CPU-only machine what would break
  (or silently copy to the host) on a GPU.
- *Every available device.* The same computations on each ``device`` (the ``device`` fixture:
  ``cpu`` and, when present, ``cuda``) must match the CPU float64 result.

The computations cover the numerical core: kernels, expectations, ``GPPosterior``, the MAP
objectives and their gradients (GPDM, HGPDM, IDDM), a fitting step, GP-ADF/RTSS filtering,
online and batch intention inference, Monte-Carlo planning and variational Bayes.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, fields

import pytest
import torch

from hgpdm_torch import expectations, settings
from hgpdm_torch.datasets import styled_movements
from hgpdm_torch.decision.lspi import LinearQ
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner
from hgpdm_torch.inference import (
    MAPInference,
    OnlineIntentionFilter,
    VariationalInference,
    infer_intention,
)
from hgpdm_torch.inference.filtering import filter_sequence, smooth
from hgpdm_torch.models import GPDM, HGPDM, IDDM

Results = dict[str, torch.Tensor]


@dataclass
class Setup:
    """Small fitted models (float64) and test windows ``z [3, 5, Dz]``."""

    gpdm: GPDM
    hgpdm: HGPDM
    discrete: IDDM
    continuous: IDDM
    z: torch.Tensor

    def to(self, device: torch.device | str) -> Setup:
        """A copy with every model and tensor on ``device``."""
        return Setup(*(copy.deepcopy(getattr(self, f.name)).to(device) for f in fields(self)))


@pytest.fixture(scope="module")
def setup() -> Setup:
    data = styled_movements(3, 4, 12, 5, noise=0.05, seed=2)
    seqs = list(data.sequences)
    alpha = (0.9, 0.3, 0.1, 1e-2)
    torch.manual_seed(0)
    gpdm = GPDM(seqs, 2, alpha=alpha)
    hgpdm = HGPDM(seqs, data.labels, 2, alpha=alpha)
    discrete = IDDM(seqs, data.labels, 2, intention="discrete", measurement="linear", alpha=alpha)
    continuous = IDDM(
        seqs, data.labels.double() / 2, 2, intention="continuous", measurement="rbf", alpha=alpha
    )
    for model in (gpdm, hgpdm, discrete, continuous):
        model.fit(3, warn=False)
    return Setup(gpdm, hgpdm, discrete, continuous, torch.stack(seqs[:3])[:, :5])


def _gaussians(model: GPDM) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussian states ``[3, Dx]``, ``[3, Dx, Dx]`` around training latents."""
    x = model.latent.detach()[:3]
    eye = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
    return x, 0.05 * eye.expand(3, -1, -1) + 0.01 * x[:, :, None] * x[:, None, :]


def kernels_and_expectations(s: Setup) -> Results:
    out = {}
    for name, model in (("hgpdm", s.hgpdm), ("discrete", s.discrete), ("continuous", s.continuous)):
        post = model.transition_posterior()
        X, k = post.train_inputs, post.kernel
        mu, Sigma = _gaussians(model)
        g = X[:3, mu.shape[1] :]
        out[f"{name} kernel"] = k(X[:6], X).to_dense()
        out[f"{name} psi0"] = expectations.psi0(k, mu, Sigma, g=g)
        out[f"{name} psi1"] = expectations.psi1(k, mu, Sigma, X, g=g)
        out[f"{name} psi2"] = expectations.psi2(k, mu, Sigma, X, g=g)
        out[f"{name} x_psi1"] = expectations.x_psi1(k, mu, Sigma, X, g=g)
    return out


def posteriors(s: Setup) -> Results:
    out = {}
    for name, model in (("gpdm", s.gpdm), ("continuous", s.continuous)):
        mu, Sigma = _gaussians(model)
        meas = model.measurement_posterior()
        out[f"{name} predict"] = torch.cat(meas.predict(mu, include_noise=True), -1)
        mean, cov, cross = meas.predict_gaussian(mu, Sigma, include_noise=True)
        out[f"{name} predict_gaussian"] = torch.cat(
            [mean.flatten(), cov.flatten(), cross.flatten()]
        )
    return out


def losses_and_gradients(s: Setup) -> Results:
    out = {}
    for name, model in (("gpdm", s.gpdm), ("hgpdm", s.hgpdm), ("iddm", s.discrete)):
        params = [p for p in model.parameters() if p.requires_grad]
        loss = model.loss()
        out[f"{name} loss"] = loss.detach()
        out[f"{name} grad"] = torch.cat([g.flatten() for g in torch.autograd.grad(loss, params)])
    return out


def fitting(s: Setup) -> Results:
    model = copy.deepcopy(s.continuous)
    # enough steps for the line search to compare close losses (a float32 closure value once
    # changed the path under a float32 default dtype)
    model.fit(25, warn=False, restarts=1)
    return {"latent after fit": model.latent.detach()}


def filtering(s: Setup) -> Results:
    model = s.continuous
    mu0, Sigma0 = _gaussians(model)
    g = model.intentions[:3]
    with settings.debug(True):  # the gated checks must keep the device too
        fr = filter_sequence(
            model.transition_posterior(), model.measurement_posterior(), s.z, mu0, Sigma0, g=g
        )
    sm = smooth(fr)
    return {"filtered": fr.cov, "log likelihood": fr.log_likelihood, "smoothed": sm.cov}


def intention_inference(s: Setup) -> Results:
    out = {}
    for name, model, options in (
        ("online", s.continuous, {}),
        ("online bound gaussian", s.continuous, {"evidence": "bound", "mixing": "gaussian"}),
        ("online class prior", s.discrete, {"state_prior": "class", "temperature": 2.0}),
        ("online sparse", s.continuous, {"inducing": 12}),
    ):
        f = OnlineIntentionFilter(model, batch_size=3, **options)
        out[name] = torch.stack([f.update(s.z[:, t]).log_prob for t in range(4)])
        f.reset([1])
        out[f"{name} reset"] = torch.cat([f.mean.flatten(), f.steps.double()])
    out["batch"] = infer_intention(s.discrete, s.z, window=3, state_prior="class").log_prob
    return out


def planning(s: Setup) -> Results:
    model = s.continuous
    f = OnlineIntentionFilter(model, forgetting=0.1)
    f.update(s.z[0, 0])
    f.update(s.z[0, 1])
    belief = Belief.from_filter(f)
    width = belief.vector().shape[-1]
    weights = torch.linspace(
        -1.0, 1.0, 3 * width, dtype=model.latent.dtype, device=model.latent.device
    )
    q = LinearQ(weights.reshape(3, width))
    out = {}
    for sampling in ("moments", "points"):
        planner = MonteCarloPlanner(
            model, f, q, lambda v: v, num_particles=64, min_particles=16, chunk_size=32,
            sampling=sampling,
        )  # fmt: skip
        gen = torch.Generator().manual_seed(5)
        out[f"project {sampling}"] = planner.project(belief, generator=gen)
        decision = planner.decide(belief, generator=gen)
        out[f"decide {sampling}"] = torch.tensor(
            [decision.action, decision.q_wait], dtype=torch.float64, device=belief.mean.device
        )
    out["step"] = planner.step(belief, s.z[:, 2]).log_prob
    return out


def variational(s: Setup) -> Results:
    # a list window is built on the CPU: VB and MAP move it to the model's device and dtype
    window = s.z[:, :4].cpu().float().tolist()
    return {
        "vb": VariationalInference(s.discrete).infer(s.z[:, :4]).log_evidence,
        "vb list": VariationalInference(s.discrete).infer(window).log_evidence,
        "map list": MAPInference(s.discrete).infer(window, steps=5).log_joint,
    }


CASES: list[Callable[[Setup], Results]] = [
    kernels_and_expectations,
    posteriors,
    losses_and_gradients,
    fitting,
    filtering,
    intention_inference,
    planning,
    variational,
]


@contextmanager
def _defaults(device: str, dtype: torch.dtype) -> Iterator[None]:
    before = torch.get_default_dtype()
    torch.set_default_device(device)
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_device(None)
        torch.set_default_dtype(before)


@pytest.mark.parametrize(
    ("default_device", "default_dtype"),
    [("meta", torch.float64), ("meta", torch.float32), ("cpu", torch.float32)],
    ids=["meta", "meta-float32", "float32"],
)
@pytest.mark.parametrize("case", CASES)
def test_no_tensor_takes_the_default_device_or_dtype(
    setup: Setup,
    case: Callable[[Setup], Results],
    default_device: str,
    default_dtype: torch.dtype,
) -> None:
    torch.manual_seed(0)
    expected = case(setup)
    with _defaults(default_device, default_dtype):
        torch.manual_seed(0)
        got = case(setup)
    for name, value in expected.items():
        assert got[name].device == value.device, name
        assert got[name].dtype == value.dtype, name
        assert torch.equal(got[name], value), name


@pytest.mark.parametrize("case", CASES)
def test_every_device_matches_cpu_float64(
    setup: Setup,
    case: Callable[[Setup], Results],
    device: torch.device,
) -> None:
    torch.manual_seed(0)
    expected = case(setup)
    torch.manual_seed(0)
    got = case(setup.to(device))
    for name, value in expected.items():
        assert got[name].device.type == device.type, name
        torch.testing.assert_close(got[name].cpu(), value, rtol=1e-6, atol=1e-8, msg=name)
