"""The online filter on every model the toolkit fits: the generic transition moments
(:class:`GenericTransition`, moment matching of the transition GP at ``[x, g_k]``) against the
IDDM fast path (:class:`SharedTransition`) where both apply, exact and sparse (``inducing``: the
same DTC posterior on both paths), Monte Carlo of the GP at points for the H-GPDM's kernels,
GP-ADF (:func:`filter_sequence`) for a plain GPDM (K = 1), and the Monte-Carlo planner on an
H-GPDM against the filter it replays."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.datasets import styled_movements, targeted_movements
from hgpdm_torch.decision.lspi import LinearQ
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner
from hgpdm_torch.inference.filtering import filter_sequence
from hgpdm_torch.inference.intention import (
    GenericTransition,
    OnlineIntentionFilter,
    SharedTransition,
    intention_grid,
    transition_moments,
)
from hgpdm_torch.models import GPDM, HGPDM, IDDM

GRID = torch.linspace(-0.9, 0.9, 7)
ALPHA = (0.9, 0.3, 0.1, 1e-3)


@pytest.fixture(scope="module")
def targets():
    return targeted_movements(12, 10, 5, noise=0.02, seed=3)


@pytest.fixture(scope="module")
def styles():
    return styled_movements(3, 4, 12, 5, noise=0.02, seed=1)


def _fitted(model, steps=15):
    model.fit(steps, warn=False)
    return model


@pytest.fixture(scope="module")
def iddm_continuous(continuous_iddm) -> IDDM:
    return continuous_iddm


@pytest.fixture(scope="module")
def iddm_discrete(styles) -> IDDM:
    return _fitted(
        IDDM(styles.sequences, styles.labels, 2, intention="discrete", measurement="linear",
             alpha=ALPHA)
    )  # fmt: skip


@pytest.fixture(scope="module")
def hgpdm_continuous(targets) -> HGPDM:
    return _fitted(HGPDM(targets.sequences, targets.labels, 2, intention="continuous", alpha=ALPHA))


@pytest.fixture(scope="module")
def hgpdm_discrete(styles) -> HGPDM:
    """Discrete g with ``sharing > 0``: a shared RBF + linear kernel plus a per-value one."""
    return _fitted(
        HGPDM(styles.sequences, styles.labels, 2, intention="discrete", sharing=0.3,
              measurement="linear", alpha=ALPHA)
    )  # fmt: skip


def _grid(model):
    return GRID if model.intention == "continuous" else None


def _stream_data(model, streams=3, steps=6):
    """``[streams, steps, Dz]`` training observations with a missing row."""
    z = torch.stack([s[:steps] for s in model.sequences()[:streams]])
    z[-1, 2] = float("nan")
    return z


def _assert_rounding_close(got, want, rel: float) -> None:
    """``got`` equals ``want`` to a relative ``rel`` of each tensor's scale (``rtol`` for the
    large entries, ``atol = rel * max |want|`` for the small ones: an off-diagonal covariance or
    a small mean carries the rounding of the whole tensor)."""
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))


def _run(f, z):
    """Beliefs and ``q(x)`` of every step: ``[T, B, K]``, ``[T, B, Dx]``, ``[T, B, Dx, Dx]``."""
    logs, means, covs = [], [], []
    for t in range(z.shape[1]):
        logs.append(f.update(z[:, t]).log_prob)
        means.append(f.mean.clone())
        covs.append(f.cov.clone())
    return torch.stack(logs), torch.stack(means), torch.stack(covs)


# ----- generic == shared where both apply ---------------------------------------------------


@pytest.mark.parametrize("which", ["iddm_continuous", "iddm_discrete"])
def test_generic_moments_equal_shared_ones(which, request, generator, gp_rounding):
    model = request.getfixturevalue(which)
    post, values = model.transition_posterior(), intention_grid(model, _grid(model))
    assert SharedTransition.supports(post, values)
    dx = model.latent_dim
    mu = model.latent[:4].detach() + 0.1 * torch.randn(4, dx, generator=generator)
    A = torch.randn(4, dx, dx, generator=generator)
    Sigma = 0.05 * A @ A.mT + 1e-4 * torch.eye(dx)
    fast = SharedTransition(post, values).moments(mu, Sigma)
    generic = GenericTransition(post, values).moments(mu, Sigma)
    for a, b in zip(generic, fast, strict=True):
        assert a.shape == b.shape == (4, len(values), dx, *a.shape[3:])
    # the same moments by other algebra: both solve with K + noise I, so they agree to
    # gp_rounding (N EPS cond(K + noise I)) of their scale (measured: up to 0.02 of it)
    _assert_rounding_close(generic, fast, gp_rounding(post))


@pytest.mark.parametrize("which", ["iddm_continuous", "iddm_discrete"])
def test_sparse_generic_moments_equal_sparse_shared_ones(which, request, generator, gp_rounding):
    """``inducing`` on both paths: one DTC posterior on the same pseudo-inputs (fewer than the
    training points, on fewer intention values for the continuous g), so the generic moment
    matching equals the grouped fast path; and both differ from the exact GP's moments."""
    model = request.getfixturevalue(which)
    post, values = model.transition_posterior(), intention_grid(model, _grid(model))
    n, dx = post.train_inputs.shape[0], model.latent_dim
    inducing = n // 2
    mu = model.latent[:4].detach() + 0.1 * torch.randn(4, dx, generator=generator)
    A = torch.randn(4, dx, dx, generator=generator)
    Sigma = 0.05 * A @ A.mT + 1e-4 * torch.eye(dx)
    paths = {}
    for path in ("shared", "generic"):
        t = transition_moments(post, values, transition=path, inducing=inducing)
        paths[path] = t
        assert type(t) is {"shared": SharedTransition, "generic": GenericTransition}[path]
    generic, shared = paths["generic"], paths["shared"]
    assert generic.inputs.shape[0] <= inducing < n  # the pseudo-inputs, not the training set
    if which == "iddm_continuous":
        assert shared.groups == round(inducing**0.5)
    fast, slow = shared.moments(mu, Sigma), generic.moments(mu, Sigma)
    exact = SharedTransition(post, values).moments(mu, Sigma)
    for a, b, c in zip(slow, fast, exact, strict=True):
        assert a.shape == b.shape == (4, len(values), dx, *a.shape[3:])
        assert float((a - c).abs().max()) > 1e-6  # a real approximation
    # one DTC by other algebra: rounding of solves with its kinv (measured: up to 0.01 of it)
    _assert_rounding_close(slow, fast, gp_rounding(generic.posterior))


@pytest.mark.parametrize("which", ["iddm_continuous", "iddm_discrete"])
def test_sparse_generic_filter_equals_sparse_shared_filter(which, request, gp_rounding):
    model = request.getfixturevalue(which)
    z = _stream_data(model)
    inducing = model.transition_posterior().train_inputs.shape[0] // 2
    out = {}
    for path in ("shared", "generic"):
        f = OnlineIntentionFilter(
            model, _grid(model), forgetting=0.1, batch_size=3, transition=path, inducing=inducing
        )
        out[path] = _run(f, z)
    # the same filter by other algebra, for T steps: T times the rounding of one step through
    # the DTC and the measurement GP (measured: up to 0.01 of it)
    (log_g, mean_g, cov_g), (log_s, mean_s, cov_s) = out["generic"], out["shared"]
    rel = z.shape[1] * gp_rounding(f.posterior, model.measurement_posterior())
    _assert_rounding_close((log_g.exp(), mean_g, cov_g), (log_s.exp(), mean_s, cov_s), rel)


def test_sparse_float32_paths_agree_with_float64(targets, generator):
    """float32 on the sparse GP: both paths compute with the float64 DTC's weights and ``kinv``
    cast. ``K_MM^-1 - noise A^-1`` refactorised in float32 is rounding noise: on this model
    (alpha_4 = 0.1, where float32 is accepted) the generic path then erred by 3% of a standard
    deviation in the mean; now both paths stay within 1e-4 and 2e-3 of a variance."""
    alpha = (*ALPHA[:3], 0.1)
    model = _fitted(IDDM(targets.sequences, targets.labels, 3, intention="continuous", alpha=alpha))
    post, values = model.transition_posterior(), intention_grid(model, GRID)
    inducing, dx = post.train_inputs.shape[0] // 3, model.latent_dim
    mu = model.latent[:6].detach() + 0.1 * torch.randn(6, dx, generator=generator)
    Sigma = 0.01 * torch.eye(dx, dtype=mu.dtype).expand(6, -1, -1)
    ref = transition_moments(post, values, transition="shared", inducing=inducing)
    mean, cov, _ = ref.moments(mu, Sigma)
    sd = torch.linalg.eigvalsh(cov)[..., :1].sqrt()  # [6, K, 1]
    for path in ("shared", "generic"):
        low = transition_moments(post, values, torch.float32, transition=path, inducing=inducing)
        m, c, _ = low.moments(mu.float(), Sigma.float())
        assert m.dtype == c.dtype == torch.float32
        assert float(((m.double() - mean).abs() / sd).max()) < 1e-3
        assert float(((c.double() - cov).abs().amax(-1) / sd**2).max()) < 1e-2


def test_points_planner_uses_the_filters_sparse_posterior(iddm_continuous):
    """``sampling="points"`` predicts particles with the filter's transition GP: the sparse one
    when the filter is sparse."""
    model = iddm_continuous
    f = OnlineIntentionFilter(model, _grid(model), inducing=20)
    q = LinearQ(torch.zeros(2, 3, dtype=torch.float64))
    planner = MonteCarloPlanner(model, f, q, lambda b: b[..., :3], sampling="points")
    assert planner.transition is f.posterior
    assert f.posterior.train_inputs.shape[0] <= 20


@pytest.mark.parametrize("which", ["iddm_continuous", "iddm_discrete"])
@pytest.mark.parametrize("evidence", ["predictive", "bound"])
def test_generic_filter_equals_shared_filter(which, evidence, request, gp_rounding):
    """Several steps, three streams (one with a missing observation): beliefs and q(x)."""
    model = request.getfixturevalue(which)
    z = _stream_data(model)
    out = {}
    for path in ("shared", "generic"):
        f = OnlineIntentionFilter(
            model, _grid(model), forgetting=0.1, batch_size=3, evidence=evidence, transition=path
        )
        kind = {"shared": SharedTransition, "generic": GenericTransition}[path]
        assert type(f.transition) is kind
        out[path] = _run(f, z)
    auto = OnlineIntentionFilter(model, _grid(model), batch_size=3, evidence=evidence)
    assert isinstance(auto.transition, SharedTransition)  # the fast path where it applies
    (log_g, mean_g, cov_g), (log_s, mean_s, cov_s) = out["generic"], out["shared"]
    # beliefs as probabilities: the over-confident bound evidence drives log beliefs of
    # unlikely values to -1e4, where equal moments still differ by a relative 1e-7. The same
    # filter by other algebra, for T steps: T times the rounding of one step through the
    # transition and measurement GPs (measured: up to 0.01 of it)
    rel = z.shape[1] * gp_rounding(auto.posterior, model.measurement_posterior())
    _assert_rounding_close((log_g.exp(), mean_g, cov_g), (log_s.exp(), mean_s, cov_s), rel)
    K = log_s.shape[-1]
    assert float(log_s[-1].exp().max()) > 1.0 / K + 0.05  # the belief moved from the prior


# ----- H-GPDM kernels: the generic path against the GP at points ------------------------------


@pytest.mark.parametrize("which", ["hgpdm_continuous", "hgpdm_discrete"])
def test_hgpdm_first_step_moments_match_monte_carlo(which, request, generator, gp_rounding):
    """The predictive moments of the first step equal (a) ``GPPosterior.predict_gaussian`` value
    by value and (b) a dense Monte Carlo of the GP predictive at points (law of total
    covariance), within 5 standard errors."""
    model = request.getfixturevalue(which)
    z = _stream_data(model, streams=2)
    f = OnlineIntentionFilter(model, _grid(model), forgetting=0.1, batch_size=2)
    assert isinstance(f.transition, GenericTransition)
    f.update(z[:, 0])
    mu, Sigma = f.mean.clone(), f.cov.clone()
    mean, cov, cross = f.transition.moments(mu, Sigma)
    post = model.transition_posterior()
    for k, g in enumerate(f.values):
        ref = post.predict_gaussian(mu, Sigma, g=g.expand(2, -1), include_noise=True)
        # all values in one batch against one value at a time: other BLAS shapes, rounding of
        # solves with K + noise I (measured: up to 0.01 of gp_rounding)
        _assert_rounding_close((mean[:, k], cov[:, k], cross[:, k]), ref, gp_rounding(post))
    S = 100_000
    for b in range(2):
        x = torch.distributions.MultivariateNormal(mu[b], Sigma[b]).sample((S,))
        for k in (0, len(f.values) - 1):
            g = f.values[k].expand(S, -1)
            m, v = post.predict(torch.cat([x, g], -1), include_noise=True)
            dm, dxx = m - m.mean(0), x - x.mean(0)
            second = dm[:, :, None] * dm[:, None, :] + torch.diag_embed(v)  # [S, Dx, Dx]
            xc = dxx[:, :, None] * dm[:, None, :]
            for est, samples in ((mean[b, k], m), (cov[b, k], second), (cross[b, k], xc)):
                se = samples.std(0) / S**0.5
                err = (samples.mean(0) - est).abs()
                assert bool((err <= 5 * se + 1e-9).all()), (which, b, k, err.max(), se.max())


@pytest.mark.parametrize("which", ["hgpdm_continuous", "hgpdm_discrete"])
def test_hgpdm_filter_runs_and_learns(which, request):
    model = request.getfixturevalue(which)
    z = _stream_data(model)
    f = OnlineIntentionFilter(model, _grid(model), forgetting=0.0, batch_size=3)
    logs, means, covs = _run(f, z)
    assert bool(torch.isfinite(logs).all() & torch.isfinite(means).all())
    torch.testing.assert_close(logs.exp().sum(-1), torch.ones(logs.shape[:-1]))
    assert float(logs[-1].exp().max()) < 1.0 or model.intention == "discrete"
    assert not bool(f.reset_count.any())
    # the bound evidence runs on the generic path too
    bound = OnlineIntentionFilter(model, _grid(model), batch_size=3, evidence="bound")
    assert bool(torch.isfinite(_run(bound, z)[0]).all())


def test_generic_path_takes_inducing_and_refuses_unknown_choices(hgpdm_continuous):
    """The H-GPDM's kernel on its sparse DTC posterior: the filter runs on the pseudo-inputs,
    and with all training points (``inducing >= N``) it tracks the exact filter (not to
    rounding: the fitted latents' ``K_MM`` is regularised to condition 1e8 by a ridge)."""
    model = hgpdm_continuous
    z = _stream_data(model)
    n = model.transition_posterior().train_inputs.shape[0]
    sparse = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=3, inducing=n // 3)
    assert isinstance(sparse.transition, GenericTransition)
    assert sparse.transition.inputs.shape[0] <= n // 3
    logs, means, _ = _run(sparse, z)
    assert bool(torch.isfinite(logs).all() & torch.isfinite(means).all())
    assert not bool(sparse.reset_count.any())
    full = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=3, inducing=n)
    exact = OnlineIntentionFilter(model, GRID, forgetting=0.1, batch_size=3)
    (log_f, mean_f, cov_f), (log_e, mean_e, cov_e) = _run(full, z), _run(exact, z)
    torch.testing.assert_close(log_f.exp(), log_e.exp(), rtol=0, atol=2e-3)
    torch.testing.assert_close(mean_f, mean_e, rtol=0, atol=1e-3 * float(mean_e.abs().max()))
    torch.testing.assert_close(cov_f, cov_e, rtol=0, atol=1e-3 * float(cov_e.abs().max()))
    with pytest.raises(ValueError, match="inducing must be a positive int"):
        OnlineIntentionFilter(model, GRID, inducing=0)
    with pytest.raises(ValueError, match="transition"):
        OnlineIntentionFilter(model, GRID, transition="fast")


# ----- a plain GPDM: one value, GP-ADF ----------------------------------------------------------


@pytest.mark.parametrize("measurement", ["rbf", "linear"])
def test_gpdm_filter_is_gp_adf(targets, measurement, gp_rounding):
    model = _fitted(GPDM(targets.sequences, 2, measurement=measurement, alpha=ALPHA))
    z = _stream_data(model)
    f = OnlineIntentionFilter(model, forgetting=0.3, batch_size=3)
    assert isinstance(f.transition, GenericTransition) and f.values.shape == (1, 0)
    logs, means, covs = _run(f, z)
    assert bool((logs == 0).all())  # the belief over one value stays 1
    fr = filter_sequence(
        model.transition_posterior(), model.measurement_posterior(), z, f.mu0, f.Sigma0
    )
    # GP-ADF by other code and shapes, for T steps: T times the rounding of one step through
    # the transition and measurement GPs (measured: up to 0.01 of it)
    rel = z.shape[1] * gp_rounding(f.posterior, model.measurement_posterior())
    _assert_rounding_close((means, covs), (fr.mean.transpose(0, 1), fr.cov.transpose(0, 1)), rel)
    with pytest.raises(ValueError, match="no intention"):
        OnlineIntentionFilter(model, GRID)


# ----- Monte-Carlo planning on an H-GPDM ---------------------------------------------------------


@pytest.mark.parametrize("which", ["hgpdm_continuous", "hgpdm_discrete"])
def test_planner_on_hgpdm_replays_its_filter(which, request, generator):
    model = request.getfixturevalue(which)
    z = _stream_data(model, streams=1)
    f = OnlineIntentionFilter(model, _grid(model), forgetting=0.1)
    for t in range(3):
        f.update(z[0, t])
    belief = Belief.from_filter(f)
    F = belief.vector().shape[0]
    q = LinearQ(torch.randn(3, F + 1, generator=generator))

    def features(v):
        return torch.cat([torch.ones_like(v[..., :1]), v], -1)

    planner = MonteCarloPlanner(model, f, q, features, num_particles=60, chunk_size=20)
    I = 12
    zi = z[0, 3] + 0.05 * torch.randn(I, model.obs_dim, generator=generator)
    mean, cov, log_prob, _ = planner.step(belief, zi)
    # The reference is the filter's update of each particle as a stream of its own: its
    # transition moments then have the planner's shapes (one Gaussian). A filter of I streams
    # computes them for I copies of the belief, which BLAS may round differently by an ulp,
    # and the evidence of the RBF measurement GP amplifies that ~3e6-fold (past 1e-9).
    ref = OnlineIntentionFilter(model, _grid(model), forgetting=0.1)
    ref.update(torch.zeros(model.obs_dim))  # start the stream, then set the belief
    outs = []
    for z_i in zi:
        ref.mean[:], ref.cov[:], ref.log_belief[:] = belief.mean, belief.cov, belief.log_prob
        out = ref.update(z_i)
        outs.append((out.log_prob, ref.mean[0].clone(), ref.cov[0].clone()))  # z_i [Dz]: [K]
    ref_log_prob, ref_mean, ref_cov = (torch.stack(v) for v in zip(*outs, strict=True))
    # the same shapes, so the same transition moments; only the conditioning algebra differs
    # (a precomputed gain): a few eps of |z| |gain| (measured: 1e-13 relative)
    torch.testing.assert_close(log_prob, ref_log_prob, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-9, atol=1e-10)
    torch.testing.assert_close(cov, ref_cov, rtol=1e-9, atol=1e-10)
    for sampling in ("moments", "points"):
        planner = MonteCarloPlanner(model, f, q, features, num_particles=60, sampling=sampling)
        r = planner.project(belief, generator=torch.Generator().manual_seed(0))
        assert r.shape == (60,) and bool(torch.isfinite(r).all())
        decision = planner.decide(belief, generator=torch.Generator().manual_seed(1))
        assert decision.action in range(4)
