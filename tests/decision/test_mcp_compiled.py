"""Monte-Carlo planning's particles on the compiled kernel
(:meth:`~hgpdm_torch.inference.intention.compiled.CompiledStep.particle_shared` and
:meth:`~hgpdm_torch.inference.intention.compiled.CompiledStep.particles`) against the same
particles in torch.

Both paths start from the same contraction of the belief's ``psi2`` and draw the same intentions
and normal deviates from the generator; the kernel conditions each particle's K predictions in
the measurement's span (the online filter's own form), torch in the observation space. The two
are the same algebra rounded differently: they differ by the rounding of one filter step
(``gp_rounding``, as the planner against the filter in ``test_phase``). The per-particle oracle
(the online filter, stream by stream) and the predictive distribution of the draws are in
``test_mcp``, which runs them with the kernels on and off. Where the kernel does not run, the
tests skip.
"""

from __future__ import annotations

import math

import pytest
import torch

from hgpdm_torch import native, settings
from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.lspi import LinearQ
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner, ParticleProjector
from hgpdm_torch.decision.stopping import belief_vector
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.observations import ObservationCheck

pytestmark = pytest.mark.skipif(
    not native.available(),
    reason="the compiled kernel does not run here: it needs an x86-64 CPU with AVX-512F and DQ "
    "and a C compiler (native.available() is False)",
)

GRID = torch.linspace(-1.2, 1.2, 9)


def _belief(model, inducing=None):
    """A filter after three frames of a training movement, and its belief."""
    f = OnlineIntentionFilter(model, GRID, forgetting=0.2, inducing=inducing)
    for z in model.sequences()[4][:3]:
        f.update(z)
    return f, Belief.from_filter(f)


def _torch_path(projector, monkeypatch):
    """The same projector with its particles in torch (the kernel's contraction kept)."""
    monkeypatch.setattr(projector, "_compiled", None)


@pytest.mark.parametrize("inducing", [None, 30])
def test_particles_equal_the_torch_particles(continuous_iddm, gp_rounding, inducing, monkeypatch):
    """Drawn particles (the same generator) and given observations (a missing row, a row with
    inf, a partly NaN row, an implausible one: treated as missing and flagged, as in torch):
    means, covariances and beliefs of both paths agree within a step's rounding; the kernel
    draws the observations torch draws."""
    f, belief = _belief(continuous_iddm, inducing)
    projector = ParticleProjector(continuous_iddm, f)
    rel = gp_rounding(f.posterior, continuous_iddm.measurement_posterior())
    shared = projector._shared(projector._check_belief(belief))
    assert type(shared).__name__ == "_CompiledShared"
    got = projector.sample_beliefs(belief, 300, torch.Generator().manual_seed(2))
    g, eps = projector._draw(shared.prob, 300, torch.Generator().manual_seed(2))
    compiled = projector._compiled
    z = compiled.particles(
        compiled.particle_args(shared.state, shared.log_prob, f.check, g, eps[..., 0])
    )[3]
    z_rows = torch.cat([z[:8], z[:1].expand(4, -1).clone()])
    z_rows[8] = math.nan  # missing
    z_rows[9, 0] = math.inf  # bad: treated as missing, flagged
    z_rows[10, 1] = math.nan  # partly NaN: bad
    z_rows[11, 2] = 1e6  # implausible: bad
    stepped = projector.step(belief, z_rows)
    _torch_path(projector, monkeypatch)
    want = projector.sample_beliefs(belief, 300, torch.Generator().manual_seed(2))
    with settings.native_kernels(False):  # the torch draws
        drawn = projector._sample_observations(
            projector._shared(projector._check_belief(belief)), 300,
            torch.Generator().manual_seed(2),
        )  # fmt: skip
    torch.testing.assert_close(z, drawn, rtol=rel, atol=rel * float(drawn.abs().max()))
    reference = projector.step(belief, z_rows)
    assert stepped.rejected.tolist() == [False] * 9 + [True] * 3
    assert torch.equal(stepped.rejected, reference.rejected)
    for a, b in (*zip(got, want, strict=True), *zip(stepped[:3], reference[:3], strict=True)):
        if b.shape[-1] == len(GRID) and b.dim() == 2:  # log-beliefs: as probabilities
            a, b = a.exp(), b.exp()
        torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))
    # the missing and the bad rows only forget, and keep the prediction's spread
    forget = torch.log_softmax(0.8 * shared.log_prob, -1)
    for i in (8, 9, 10, 11):
        torch.testing.assert_close(stepped.log_prob[i], forget, rtol=0, atol=1e-14)
        torch.testing.assert_close(stepped.cov[i], stepped.cov[8], rtol=0, atol=0)


def test_decisions_equal_the_torch_decisions(continuous_iddm, gp_rounding, monkeypatch):
    """A whole decision (Algorithm 4.3 with and without early termination): the same action,
    particles used and, within a step's rounding of the values, the same value of waiting."""
    f, belief = _belief(continuous_iddm)
    features = len(belief.vector())
    weights = torch.randn(4, features, generator=torch.Generator().manual_seed(0),
                          dtype=torch.float64)  # fmt: skip
    planner = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights), lambda v: v)
    rel = gp_rounding(f.posterior, continuous_iddm.measurement_posterior())

    def decisions():
        out = []
        for early in (True, False):
            gen = torch.Generator().manual_seed(9)
            out.append(planner.decide(belief, early_stop=early, generator=gen))
        return out

    got = decisions()
    _torch_path(planner, monkeypatch)
    for a, b in zip(got, decisions(), strict=True):
        assert (a.action, a.particles) == (b.action, b.particles)
        scale = float(weights.abs().sum(1).max()) * float(belief_vector(
            belief.mean, belief.cov, belief.log_prob.exp()).abs().max() + 10.0)  # fmt: skip
        assert a.q_wait == pytest.approx(b.q_wait, abs=rel * scale)


def test_the_torch_path_takes_over_where_the_kernel_does_not_run(continuous_iddm, monkeypatch):
    """The torch particles where the kernel may not run (kernels off, debug checks, the literal
    sampler; float32 and other devices are refused by native.usable, as for the filter's step)
    and where a belief's shared factors do not factorise in the kernel (a negative measurement
    noise)."""
    f, belief = _belief(continuous_iddm)
    projector = ParticleProjector(continuous_iddm, f)

    def kind():
        return type(projector._shared(projector._check_belief(belief))).__name__

    assert kind() == "_CompiledShared"
    with settings.native_kernels(False):
        assert kind() == "_Shared"
    with settings.debug():
        assert kind() == "_Shared"
    assert ParticleProjector(continuous_iddm, f, sampling="points")._compiled is None
    compiled = projector._compiled
    meas = compiled.meas.clone()
    meas[-2] = -1e3  # the noise: no innovation covariance factorises
    monkeypatch.setattr(compiled, "meas", meas)
    assert compiled.particle_shared(belief.mean, belief.cov, belief.log_prob, None) is None


def test_particle_inputs_are_checked(continuous_iddm):
    """Grid values outside 0 .. K - 1 and operands of another dtype or shape are refused before
    the kernel reads them."""
    f, belief = _belief(continuous_iddm)
    projector = ParticleProjector(continuous_iddm, f)
    shared = projector._shared(projector._check_belief(belief))
    compiled = projector._compiled
    noise = torch.zeros(3, f.obs_dim, dtype=torch.float64)
    args = (shared.state, shared.log_prob, f.check)
    with pytest.raises(ValueError, match="grid values"):
        compiled.particles(compiled.particle_args(*args, torch.tensor([0, len(GRID), 1]), noise))
    with pytest.raises(TypeError, match="int64"):
        draws = torch.tensor([0, 1, 1], dtype=torch.int32)
        compiled.particles(compiled.particle_args(*args, draws, noise))
    with pytest.raises(ValueError, match="noise"):
        compiled.particles(compiled.particle_args(*args, None, noise[:, :2].contiguous()))
    with pytest.raises(TypeError, match="float64"):
        compiled.particles(compiled.particle_args(*args, None, noise.float()))
    with pytest.raises(TypeError, match="CPU"):  # a device's pointer never reaches the kernel
        meta = torch.zeros(3, dtype=torch.int64, device="meta")
        compiled.particles(compiled.particle_args(*args, meta, noise))
    d, dz, _ = compiled.particle_args(*args, None, noise).dims
    with pytest.raises(ValueError, match="rank"):  # beyond min(D, Dz): the kernel's registers
        compiled.particles(compiled.particle_args(*args, None, noise)._replace(dims=(d, dz, d + 1)))


def test_a_check_without_threshold_is_finiteness_alone(continuous_iddm):
    """A check without an outlier threshold uses every finite row, as ObservationCheck.usable
    does, even where a channel's spread is 0 (its limit, inf times 0, is NaN)."""
    f, belief = _belief(continuous_iddm)
    projector = ParticleProjector(continuous_iddm, f)
    shared = projector._shared(projector._check_belief(belief))
    spread = f.check.spread.clone()
    spread[0] = 0.0
    check = ObservationCheck(f.check.center, spread, None)
    rows = continuous_iddm.sequences()[4][3:7].clone()
    assert bool(check.usable(rows).all())
    compiled = projector._compiled
    got = compiled.particles(
        compiled.particle_args(shared.state, shared.log_prob, check, None, rows)
    )
    want = compiled.particles(
        compiled.particle_args(shared.state, shared.log_prob, None, None, rows)
    )
    for a, b in zip(got, want, strict=True):
        assert torch.equal(a, b)
    forgot = torch.log_softmax(0.8 * shared.log_prob, -1)  # a missing row only forgets
    assert not torch.allclose(got[2][0], forgot)


def test_step_uses_the_filters_classification_of_each_row(continuous_iddm, monkeypatch):
    """``step`` classifies each row in the observations' own dtype (as the filter does) and the
    kernel follows it: a float32 row at the edge of the outlier limit that float32 accepts and
    float64 would refuse is used on both paths, and its update is the torch path's."""
    f = OnlineIntentionFilter(continuous_iddm, GRID, forgetting=0.2, outlier_sd=3.0)
    for z in continuous_iddm.sequences()[4][:3]:
        f.update(z)
    belief = Belief.from_filter(f)
    projector = ParticleProjector(continuous_iddm, f)
    row = continuous_iddm.sequences()[4][3].to(torch.float32)
    # float32 values around the limit in each channel, until one that float32 accepts and
    # float64 refuses (the float32 check rounds the centre, the limit and the difference)
    found = False
    for channel in range(row.shape[0]):
        edge = (f.check.center[channel] + f.check.limit[channel]).to(torch.float32)
        for step in range(-64, 64):
            row[channel] = edge + step * torch.finfo(torch.float32).eps * edge.abs()
            if bool(f.check.usable(row)) and not bool(f.check.usable(row.double())):
                found = True
                break
        if found:
            break
        row[channel] = continuous_iddm.sequences()[4][3][channel]
    if not found:
        pytest.skip("no float32 value rounds inside this model's limits")
    z = torch.stack([row, row - 1e-3])
    got = projector.step(belief, z)
    assert not bool(got.rejected.any())
    _torch_path(projector, monkeypatch)
    want = projector.step(belief, z)
    for a, b in zip(got[:3], want[:3], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6 * float(b.abs().max()))


@pytest.mark.parametrize("bias", [False, True])
def test_default_values_equal_torchs(continuous_iddm, bias, monkeypatch):
    """The particles' LSPI values for the default belief vectors and a fitted RadialBasis, by the
    kernel and by belief_vector, RadialBasis and LinearQ in torch: the same up to the rounding of
    the exponents (each a sum of F ~ 20 products of standardised coordinates, |exponent| up to
    ~50: 1e-13 absolute, through exp and a product with weights of sum ~ 10)."""
    f, belief = _belief(continuous_iddm)
    projector = ParticleProjector(continuous_iddm, f)
    mean, cov, log_prob = projector.sample_beliefs(belief, 203, torch.Generator().manual_seed(1))
    vectors = belief_vector(mean, cov, log_prob.exp())
    basis = RadialBasis(40, bias=bias, seed=0).fit(vectors)
    gen = torch.Generator().manual_seed(3)
    weights = torch.randn(4, basis.num_features, generator=gen, dtype=torch.float64)
    planner = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights), basis)
    got = planner._values(mean, cov, log_prob)
    want = LinearQ(weights).values(basis(vectors))
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12 * float(weights.abs().sum(1).max()))
    # another vectorize (the same vectors, checked) takes the torch path: whole decisions agree
    monkeypatch.setattr(planner, "vectorize", belief_vector)
    for early in (False, True):
        a = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights), basis).decide(
            belief, early_stop=early, generator=torch.Generator().manual_seed(4)
        )
        b = planner.decide(belief, early_stop=early, generator=torch.Generator().manual_seed(4))
        assert (a.action, a.particles) == (b.action, b.particles)
        assert a.q_wait == pytest.approx(b.q_wait, abs=1e-12)
    # the path is chosen at each call: a feature map, belief vectors or values replaced after
    # construction are used (here each doubles or shifts the values: the kernel's would not)
    fresh = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights), basis)
    monkeypatch.setattr(fresh, "features", lambda v: 2.0 * basis(v))
    torch.testing.assert_close(fresh._values(mean, cov, log_prob), 2.0 * want)
    fresh = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights), basis)
    monkeypatch.setattr(fresh, "vectorize", lambda m, c, p: belief_vector(m, c, p) + 1.0)
    torch.testing.assert_close(
        fresh._values(mean, cov, log_prob), LinearQ(weights).values(basis(vectors + 1.0))
    )

    class Shifted(LinearQ):
        def values(self, phi):
            return super().values(phi) + 1.0

    fresh = MonteCarloPlanner(continuous_iddm, f, Shifted(weights), basis)
    torch.testing.assert_close(fresh._values(mean, cov, log_prob), want + 1.0)
    # a non-finite belief raises torch's error, as without the kernel
    fresh = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights), basis)
    with pytest.raises(ValueError, match="NaN or inf"):
        fresh._values(mean.clone().fill_(math.nan), cov, log_prob)


def test_particle_values_are_the_values_of_the_particles(continuous_iddm, monkeypatch):
    """The particles' values in one call (``particle_values``) against ``rbf_values`` of the
    beliefs ``particles`` returns for the same arguments (drawn; given, with missing, inf,
    partly-NaN and implausible rows): the same but for the vectors' probabilities, the
    mixture's normalised weights instead of exp of the normalised log-belief (a few ulp of
    each, through the exponent's sum of F ~ 20 products: the bound of the test above). A
    non-finite value sends the decision through the particles and torch's values."""
    f = OnlineIntentionFilter(continuous_iddm, GRID, forgetting=0.2, outlier_sd=3.0)
    for z in continuous_iddm.sequences()[4][:3]:
        f.update(z)
    belief = Belief.from_filter(f)
    projector = ParticleProjector(continuous_iddm, f)
    mean, cov, log_prob = projector.sample_beliefs(belief, 203, torch.Generator().manual_seed(1))
    basis = RadialBasis(40, bias=True, seed=0).fit(belief_vector(mean, cov, log_prob.exp()))
    weights = torch.randn(4, basis.num_features, generator=torch.Generator().manual_seed(3))
    planner = MonteCarloPlanner(continuous_iddm, f, LinearQ(weights.double()), basis)
    shared = planner._shared(planner._check_belief(belief))
    parameters = planner._native_basis(f.mu0.shape[0], len(GRID))
    compiled, tol = planner._compiled, 1e-12 * float(weights.abs().sum(1).max())
    drawn = planner._compiled_args(shared, 203, torch.Generator().manual_seed(2))
    observed = continuous_iddm.sequences()[4][3:16].clone()
    observed[1], observed[2, 0], observed[3, 1] = math.nan, math.inf, math.nan
    observed[4, 0] = f.check.center[0] + 2 * f.check.limit[0]
    given = compiled.particle_args(shared.state, shared.log_prob, f.check, None, observed)
    # without a check, a row with an inf channel is treated as missing (finiteness alone), as
    # the missing (all-NaN) row is
    rows = observed[[1, 0]].clone()
    rows[1, 0] = math.inf
    unchecked_args = compiled.particle_args(shared.state, shared.log_prob, None, None, rows)
    unchecked = compiled.particle_values(unchecked_args, *parameters, 1)
    assert unchecked.isfinite().all() and unchecked[0] == unchecked[1]
    for args in (drawn, given):
        values = planner._values(*compiled.particles(args)[:3])
        for first in (0, 1, 3):
            got = compiled.particle_values(args, *parameters, first)
            want = values[:, first:].max(-1).values
            torch.testing.assert_close(got, want, rtol=0, atol=tol)
        spoilt = parameters[1].clone()  # a NaN weight of action 2 spoils only its maxima
        spoilt[2, 0] = math.nan
        assert bool(compiled.particle_values(args, parameters[0], spoilt, 0).isnan().all())
        assert compiled.particle_values(args, parameters[0], spoilt, 3).isfinite().all()
    decided = planner.decide(belief, early_stop=False, generator=torch.Generator().manual_seed(4))
    monkeypatch.setattr(
        compiled, "particle_values", lambda *a: torch.full((500,), math.nan, dtype=torch.float64)
    )
    again = planner.decide(belief, early_stop=False, generator=torch.Generator().manual_seed(4))
    assert (again.action, again.particles) == (decided.action, decided.particles)
    assert again.q_wait == pytest.approx(decided.q_wait, abs=tol)


def test_rank_space_conditioning_and_its_count(continuous_iddm, gp_rounding):
    """The kernel's conditioning written out in torch from its shared state (``z~ = (z -
    offset) / scale``, ``zu = U^T z~``, the residual off U's span, ``a = G zu - c``, ``m + A^T
    a``, the log-density, then the filter's belief step and mixture): the same particles as
    the kernel's; and its matrix products, counted by ``torch.utils.flop_counter``, are the
    floor's per-particle conditioning less its elementwise terms (the scaling and the
    residual's squares, ``2 Dz``; the Mahalanobis squares, ``K k``) and with G dense (``K k^2``
    where the count has its triangle, ``K k (k + 1) / 2``)."""
    from torch.utils.flop_counter import FlopCounterMode

    from hgpdm_torch.gaussian import mixture_moments
    from hgpdm_torch.inference.intention.measurement import linear_measurement
    from hgpdm_torch.intention_belief import belief_step

    f, belief = _belief(continuous_iddm)
    vector = belief.vector()
    planner = MonteCarloPlanner(
        continuous_iddm, f, LinearQ(torch.zeros(4, len(vector))), lambda v: v
    )
    shared = planner._shared(planner._check_belief(belief))
    g, eps = planner._draw(shared.prob, 64, torch.Generator().manual_seed(5))
    compiled = planner._compiled
    args = compiled.particle_args(shared.state, shared.log_prob, f.check, g, eps[..., 0])
    mean, cov, log_prob, z = compiled.particles(args)
    linear = linear_measurement(f.measure)
    K, dx, dz, k = len(GRID), f.mu0.shape[0], f.obs_dim, linear.R.shape[0]
    sizes = (dx, dx * dx, dx * dx, k * dx, k * k, k, 1, 1, dz, dz * dz)
    m, P, Ppost, A, G, c, iv, logdet, _, _ = shared.state.split(sizes, -1)
    A, G = A.view(K, k, dx), G.view(K, k, k)
    n = z.shape[0]
    with FlopCounterMode(display=False) as counter:
        zs = (z - linear.offset) / linear.scale
        zu = zs @ linear.U
        perp = (zs - zu @ linear.U.T).pow(2).sum(-1)
        a = torch.einsum("kqo,io->ikq", G, zu) - c
        means = m + torch.einsum("ikq,kqd->ikd", a, A)
    maha = a.pow(2).sum(-1) + perp[:, None] * iv[:, 0]
    evidence = -0.5 * (maha + logdet[:, 0] + dz * math.log(2 * math.pi))
    options = f.options.belief
    new = belief_step(shared.log_prob.expand(n, K), evidence, torch.ones(n, dtype=torch.bool),
                      options.forgetting, options.temperature)  # fmt: skip
    want_mean, want_cov = mixture_moments(new.exp(), means, Ppost.view(K, dx, dx))
    rel = gp_rounding(f.posterior, continuous_iddm.measurement_posterior())
    for got, want in ((mean, want_mean), (cov, want_cov), (log_prob.exp(), new.exp())):
        torch.testing.assert_close(got, want, rtol=rel, atol=rel * float(want.abs().max()))

    products = counter.get_total_flops() / 2 / n
    one = planner.operations(n + 1).madds - planner.operations(n).madds
    conditioning = one - planner.q.weights.numel() - (2 * K * dx * dx + K * dx) - dz * (dz + 1) // 2
    assert products == conditioning - 2 * dz - K * k - K * k * (k + 1) // 2 + K * k * k
