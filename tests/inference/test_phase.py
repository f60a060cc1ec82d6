"""The phase-aware IDDM (``IDDM(phase_width=...)``): its kernel, its transition GP's inputs and the
online filter that counts each stream's phase.

Oracles: the kernel against its closed form; the moments at a Gaussian input against Monte Carlo
of the GP's predictive mean at sampled points; a narrow phase factor against GPs trained on one
phase's transitions only (a filter that used the wrong phase at any step would differ); a very
wide one against the thesis's kernel (same latents, no fit in between).
"""

from __future__ import annotations

import math

import pytest
import torch

from hgpdm_torch import settings
from hgpdm_torch.datasets import targeted_movements
from hgpdm_torch.decision.mcp import Belief, ParticleProjector
from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.inference import VariationalInference
from hgpdm_torch.inference.intention import (
    GenericTransition,
    OnlineIntentionFilter,
    SharedTransition,
    infer_intention,
    transition_moments,
)
from hgpdm_torch.kernels import transition_kernel
from hgpdm_torch.models import IDDM, load_model

GRID = torch.linspace(-0.9, 0.9, 5)
ALPHA = (0.9, 0.3, 0.1, 1e-2)


@pytest.fixture(scope="module")
def data():
    return targeted_movements(8, 6, 4, noise=0.02, seed=5)


def _model(data, phase_width, fit=False, intention="continuous"):
    torch.manual_seed(0)
    g = data.labels if intention == "continuous" else (data.labels > 0).long()
    model = IDDM(
        data.sequences, g, 2, intention=intention, measurement="linear", alpha=ALPHA,
        phase_width=phase_width,
    )  # fmt: skip
    if fit:
        model.fit(10, warn=False)
    return model


@pytest.mark.parametrize("kind", ["iddm_continuous", "iddm_discrete"])
def test_phase_kernel_is_the_product_with_an_rbf_over_the_last_column(kind):
    torch.manual_seed(1)
    base = transition_kernel(kind, 3, g_dim=2, num_values=3, alpha=ALPHA).double()
    phased = transition_kernel(kind, 3, g_dim=2, num_values=3, alpha=ALPHA, phase_width=1.5)
    gd = 2 if kind == "iddm_continuous" else 1
    X = torch.randn(7, 3 + gd + 1, dtype=torch.float64)
    if kind == "iddm_discrete":
        X[:, 3] = torch.randint(0, 3, (7,)).double()
    d = X[:, -1:] - X[:, -1:].T
    want = base(X[:, :-1]).to_dense() * torch.exp(-(d**2) / (2 * 1.5**2))
    got = phased.double()(X).to_dense()
    # entries of order 1, one product each: a few ulp
    torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-15)


def test_phase_width_is_checked():
    with pytest.raises(ValueError, match="phase_width applies to the IDDM kinds"):
        transition_kernel("gpdm", 2, phase_width=1.0)
    for bad in (0.0, -1.0, math.inf, True, "2"):
        with pytest.raises(ValueError, match="phase_width must be a positive number"):
            transition_kernel("iddm_continuous", 2, phase_width=bad)
        with pytest.raises(ValueError, match="phase_width must be a positive number"):
            IDDM([torch.randn(5, 3)], torch.zeros(1), 2, intention="continuous", phase_width=bad)


def test_transition_inputs_carry_the_frame_index_and_the_model_saves_it(data, tmp_path):
    model = _model(data, 2.0)
    inputs = model.transition_inputs(model.latent.detach())
    want = torch.cat([torch.arange(len(s) - 1) for s in data.sequences]).double()
    assert inputs.shape[1] == 2 + 1 + 1
    torch.testing.assert_close(inputs[:, -1], want, rtol=0, atol=0)
    torch.testing.assert_close(inputs[:, :-1], _model(data, None).transition_inputs(model.latent))
    model.save(tmp_path / "m.pt")
    loaded = load_model(tmp_path / "m.pt")
    assert loaded.phase_width == 2.0
    torch.testing.assert_close(loaded.transition_inputs(loaded.latent.detach()), inputs)
    # a rollout feeds the step index as the phase
    out = model.rollout(model.latent[0].detach(), 3, g=0.2)
    post = model.transition_posterior()
    x = model.latent[0].detach()
    for step in range(3):
        x, _ = post.predict(torch.cat([x, x.new_tensor([0.2, float(step)])])[None])
        x = x[0]
        torch.testing.assert_close(out[step + 1], x, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("path", ["generic", "shared"])
def test_moments_with_phase_match_monte_carlo(data, path):
    model = _model(data, 1.0, fit=True)
    post = model.transition_posterior()
    moments = transition_moments(post, GRID[:, None].double(), phase=True, transition=path)
    assert isinstance(moments, {"generic": GenericTransition, "shared": SharedTransition}[path])
    gen = torch.Generator().manual_seed(2)
    mu = model.latent.detach()[[1, 9]]
    Sigma = 0.05 * torch.eye(2, dtype=mu.dtype).expand(2, 2, 2)
    phase = torch.tensor([1.0, 3.0], dtype=mu.dtype)
    mean, cov, _ = moments.moments(mu, Sigma, phase)
    n = 200_000
    for b in range(2):
        x = mu[b] + 0.05**0.5 * torch.randn(n, 2, generator=gen, dtype=mu.dtype)
        for k in (0, 2, 4):
            known = x.new_tensor([float(GRID[k]), float(phase[b])]).expand(n, 2)
            m, v = post.predict(torch.cat([x, known], -1))
            mc_mean = m.mean(0)
            # the law of total variance: Var[f] = E[Var f | x] + Var[E f | x], plus alpha_4
            mc_cov = torch.cov(m.T) + torch.diag_embed(v.mean(0)) + post.noise * torch.eye(2)
            sd = m.std(0) / n**0.5  # Monte Carlo standard error of the mean
            assert ((mean[b, k] - mc_mean).abs() < 5 * sd + 1e-12).all()
            torch.testing.assert_close(cov[b, k], mc_cov.to(cov), rtol=0.02, atol=2e-3 * float(
                mc_cov.diagonal().max()))  # fmt: skip


@pytest.mark.parametrize("intention", ["continuous", "discrete"])
def test_shared_phase_path_equals_the_generic_one(data, intention, gp_rounding):
    """The phase-aware IDDM on the shared (fused) path: the phase factor rescales each training
    point per stream, the same moments as moment matching at [x, g, p] (the generic path), and
    the same beliefs over 6 steps of 3 streams; the filter picks the shared path by default."""
    model = _model(data, 1.0, intention=intention, fit=True)
    post = model.transition_posterior()
    grid = GRID if intention == "continuous" else None
    shared = OnlineIntentionFilter(model, grid, forgetting=0.1, batch_size=3)
    generic = OnlineIntentionFilter(model, grid, forgetting=0.1, batch_size=3,
                                    transition="generic")  # fmt: skip
    assert isinstance(shared.transition, SharedTransition)
    mu = model.latent.detach()[[0, 4, 9]]
    Sigma = 0.05 * torch.eye(2, dtype=mu.dtype).expand(3, 2, 2)
    phase = torch.tensor([0.0, 2.0, 4.0], dtype=mu.dtype)
    # the same moments by other algebra and shapes: the rounding of solves with K + noise I
    # (gp_rounding) of each quantity's scale
    rel = gp_rounding(post)
    got = shared.transition.moments(mu, Sigma, phase)
    want = generic.transition.moments(mu, Sigma, phase)
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))
    z = torch.stack([data.sequences[j] for j in (0, 5, 6)])
    rel = 6 * gp_rounding(post, model.measurement_posterior())
    for t in range(6):
        a, b = shared.update(z[:, t]), generic.update(z[:, t])
        torch.testing.assert_close(a.prob, b.prob, rtol=rel, atol=rel)


def test_filter_uses_each_steps_phase(data):
    """With a narrow phase factor (0.05 frames: other phases weigh exp(-200)), step t's transition
    is the GP of the transitions out of frame t - 1 alone: a filter run step by step on those
    per-phase GPs (no phase column) gives the same beliefs."""
    model = _model(data, 0.05, fit=True)
    base = _model(data, None)
    with torch.no_grad():
        base.latent.copy_(model.latent)
        base.raw_scales.copy_(model.raw_scales)
        base.raw_measurement_noise.copy_(model.raw_measurement_noise)
        base.raw_transition_noise.copy_(model.raw_transition_noise)
        base.measurement_kernel.load_state_dict(model.measurement_kernel.state_dict())
    z = torch.stack([s for s in data.sequences[:3]])  # [3, T, Dz], every stream from frame 0
    f = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=3)
    ref = OnlineIntentionFilter(base, GRID, forgetting=0.1, batch_size=3, transition="generic")
    full = base.transition_posterior()
    phases = model.transition_phases()
    x = model.latent.detach()
    for t in range(z.shape[1]):
        if t > 0:  # the transition out of frame t - 1: that phase's pairs only
            rows = phases == t - 1
            ref.transition = GenericTransition(
                GPPosterior(full.kernel, base.transition_inputs(x)[rows],
                            base.transition_targets(x)[rows], full.noise),
                ref.values,
            )  # fmt: skip
        got, want = f.update(z[:, t]), ref.update(z[:, t])
        # beliefs of order 1 from sums of O(10) log-evidence terms: the neglected kernel
        # weight exp(-200) is far below rounding
        torch.testing.assert_close(got.log_prob, want.log_prob, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(f.mean, ref.mean, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("intention", ["continuous", "discrete"])
def test_wide_phase_factor_gives_back_the_thesis_kernel(data, intention):
    """Same latents and hyperparameters (no fit): a phase width of 1e6 frames changes the kernel
    by a factor exp(-25 / 2e12) ~ 1 - 1e-11, so the beliefs agree to about that."""
    grid = GRID if intention == "continuous" else None
    a = OnlineIntentionFilter(_model(data, 1e6, intention=intention), grid, batch_size=2)
    b = OnlineIntentionFilter(_model(data, None, intention=intention), grid, batch_size=2,
                              transition="generic")  # fmt: skip
    for t in range(6):
        zt = torch.stack([data.sequences[0][t], data.sequences[5][t]])
        torch.testing.assert_close(a.update(zt).log_prob, b.update(zt).log_prob, rtol=1e-7,
                                   atol=1e-7)  # fmt: skip


def test_phase_model_is_refused_where_no_phase_is_known(data):
    model = _model(data, 1.0)
    z = data.sequences[0][None, :4]
    with pytest.raises(ValueError, match="windows carry no phase"):
        infer_intention(model, z, GRID)
    with pytest.raises(ValueError, match="window inference carries no phase"):
        VariationalInference(model)
    with pytest.raises(ValueError, match="inducing"):
        OnlineIntentionFilter(model, GRID, inducing=10)
    post, values = model.transition_posterior(), GRID[:, None].double()
    assert not SharedTransition.supports(post, values)  # without its phase
    with pytest.raises(ValueError, match="needs phase=True"):
        SharedTransition(post, values)
    with pytest.raises(ValueError, match="inducing"):
        SharedTransition(post, values, phase=True, inducing=10)
    f = OnlineIntentionFilter(model, GRID)
    with pytest.raises(ValueError, match="pass phase"):
        f.transition.moments(model.latent[:1].detach(), torch.eye(2)[None].double())


def test_particles_replay_the_filter_at_the_beliefs_phase(data, gp_rounding):
    """Monte-Carlo planning's particle update (Algorithm 4.2) of a phase-aware IDDM's belief
    after 3 observations equals the online filter's update of streams in that belief at that
    phase; the moment and point samplers of the next observation agree in its moments (with a
    linear measurement kernel both are exact), and a belief without its phase is refused."""
    model = _model(data, 0.5, fit=True)
    f = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=2)
    for t in range(3):
        f.update(torch.stack([data.sequences[1][t], data.sequences[6][t]]))
    belief = Belief.from_filter(f, 1)
    assert belief.phase == 2  # x_t is frame 2 of the stream
    projector = ParticleProjector(model, f)
    gen = torch.Generator().manual_seed(4)
    z = data.sequences[6][3] + 0.05 * torch.randn(30, model.obs_dim, generator=gen,
                                                  dtype=torch.float64)  # fmt: skip
    mean, cov, log_prob, rejected = projector.step(belief, z)
    ref = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=30)
    ref.update(torch.zeros(30, model.obs_dim, dtype=torch.float64))  # start, then overwrite
    ref.mean[:], ref.cov[:], ref.log_belief[:] = belief.mean, belief.cov, belief.log_prob
    ref.steps[:] = 3
    out = ref.update(z)
    # batched gain against per-stream updates: rounding of solves with K + noise I (test_mcp)
    rounding = gp_rounding(f.posterior)
    for a, b in ((log_prob, out.log_prob), (mean, ref.mean), (cov, ref.cov)):
        torch.testing.assert_close(a, b, rtol=rounding, atol=rounding * float(b.abs().max()))
    # another phase gives other dynamics, so the comparison above can fail
    other = projector.step(Belief(belief.mean, belief.cov, belief.log_prob, 0), z)
    assert (other.log_prob - log_prob).abs().max() > 1e-3
    points = ParticleProjector(model, f, sampling="points")
    with settings.native_kernels(False):  # the torch samplers (the kernel's: test_mcp)
        shared = projector._shared(projector._check_belief(belief))
    n = 20000
    za = projector._sample_observations(shared, n, torch.Generator().manual_seed(1))
    zb = points._sample_observations(shared, n, torch.Generator().manual_seed(2))
    se = torch.sqrt(za.var(0) / n + zb.var(0) / n)
    assert ((za.mean(0) - zb.mean(0)).abs() < 4.5 * se).all()
    with pytest.raises(ValueError, match="needs its phase"):
        projector.step(Belief(belief.mean, belief.cov, belief.log_prob), z)
    with pytest.raises(ValueError, match="int >= 0"):
        projector.step(Belief(belief.mean, belief.cov, belief.log_prob, -1), z)
    plain = _model(data, None)
    g = OnlineIntentionFilter(plain, GRID)
    with pytest.raises(ValueError, match="phase-aware IDDM"):
        ParticleProjector(plain, g).step(Belief(belief.mean, belief.cov, belief.log_prob, 2), z)
