"""BeliefMixture: the weighted average of member beliefs against a direct numpy computation,
the online stream against the batch beliefs, and bad input."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from hgpdm_torch.inference import BeliefMixture
from hgpdm_torch.models import LinearIDDM


def _members(generator: torch.Generator, discrete: bool = False):
    """Two LinearIDDMs (no interaction, rank 1) fitted to sequences whose next frame depends on
    g times the current one, and 10 held-out sequences."""
    n, t = 70, 5
    g = torch.randint(0, 3, (n,), generator=generator).double() if discrete else (
        2 * torch.rand(n, generator=generator) - 1
    )  # fmt: skip
    z = [torch.randn(n, 2, generator=generator)]
    for _ in range(t - 1):
        drift = torch.stack([0.5 * g * z[-1][:, 0], 0.4 * g], -1)
        z.append(0.7 * z[-1] + drift + 0.3 * torch.randn(n, 2, generator=generator))
    obs = torch.stack(z, 1)
    labels = g.long() if discrete else g
    kind = "discrete" if discrete else "continuous"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # edge choices of the prior scales
        models = [LinearIDDM(intention=kind, interaction_rank=r).fit(obs[:60], labels[:60])
                  for r in (0, 1)]  # fmt: skip
    return models, obs[60:]


@pytest.mark.parametrize("discrete", [False, True])
def test_mixture_is_the_weighted_average_of_the_members(discrete, generator):
    models, test = _members(generator, discrete)
    mix = BeliefMixture(models, weights=[3.0, 1.0])
    assert mix.weights == [0.75, 0.25]
    belief = mix.beliefs(test)
    parts = [m.beliefs(test).prob.numpy() for m in models]
    expected = 0.75 * parts[0] + 0.25 * parts[1]  # computed directly, in numpy
    np.testing.assert_allclose(belief.prob.numpy(), expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(belief.log_prob.exp().numpy(), expected, rtol=1e-12, atol=1e-15)
    values = models[0].grid().numpy()
    if discrete:
        assert belief.mean is None
    else:
        np.testing.assert_allclose(belief.mean.numpy(), expected @ values, rtol=1e-12)
        var = expected @ values**2 - (expected @ values) ** 2
        np.testing.assert_allclose(belief.std.numpy() ** 2, var, rtol=1e-9, atol=1e-12)
    # the members disagree: the mixture differs from each, and one member alone is itself
    assert not np.allclose(parts[0], parts[1], atol=1e-3)
    alone = BeliefMixture(models[:1]).beliefs(test)
    torch.testing.assert_close(alone.prob, models[0].beliefs(test).prob, rtol=1e-12, atol=1e-15)


def test_stream_matches_beliefs_and_flags_a_bad_row(generator):
    models, test = _members(generator)
    grid = torch.linspace(-1, 1, 9, dtype=torch.float64)
    mix = BeliefMixture(models)
    batch = mix.beliefs(test, grid)
    stream = mix.stream(len(test), grid)
    for t in range(test.shape[1]):
        step = stream.update(test[:, t])
        torch.testing.assert_close(step.prob, batch.prob[:, t], rtol=1e-10, atol=1e-12)
        assert not bool(step.rejected.any())
    stream.reset()
    frames = test[:, :3].clone()
    frames[2, 1, 0] = float("inf")
    for t in range(3):
        step = stream.update(frames[:, t])
    assert not bool(step.rejected.any())  # the bad row was one frame back
    # as the online filter: a bad row (inf, partly NaN, 1e200: implausible) is rejected and
    # flagged, a row of NaN is missing and not flagged; the other streams are untouched
    for bad, flagged in ((float("inf"), True), (1e200, True), (float("nan"), False)):
        stream.reset()
        frames = test[:, :3].clone()
        frames[2, 1, 0] = bad
        if flagged is False:
            frames[2, 1] = bad  # the whole row
        stream.update(frames[:, 0])
        step = stream.update(frames[:, 1])
        assert step.rejected.tolist() == [flagged and j == 2 for j in range(10)]
        assert bool(torch.isfinite(step.log_prob).all())
        others = [j for j in range(10) if j != 2]
        torch.testing.assert_close(step.prob[others], batch.prob[others, 1], rtol=1e-10, atol=1e-12)
        # stream 2 took no evidence into or out of the frame: still its prior
        torch.testing.assert_close(step.prob[2], batch.prob[2, 0], rtol=1e-10, atol=1e-12)
        step = stream.update(frames[:, 2])
        torch.testing.assert_close(step.prob[2], batch.prob[2, 0], rtol=1e-10, atol=1e-12)
    # the batch beliefs refuse the bad frame, naming it
    frames[2, 1] = 1e200
    with pytest.raises(ValueError, match=r"obs\[2, 1\] cannot be used"):
        mix.beliefs(frames, grid)


class _FlagsFirst:
    """A member whose stream flags stream 0's every frame as rejected (another rule than its
    partner's), otherwise the wrapped model."""

    def __init__(self, model: LinearIDDM) -> None:
        self.model = model

    def grid(self, values=None):
        return self.model.grid(values)

    def beliefs(self, obs, grid=None, log_prior=None):
        return self.model.beliefs(obs, grid, log_prior)

    def stream(self, batch_size=1, grid=None, log_prior=None):
        inner = self.model.stream(batch_size, grid, log_prior)

        class Stream:
            def update(self, z):
                belief = inner.update(z)
                belief.rejected = torch.arange(batch_size) == 0
                return belief

        return Stream()


def test_stream_rejects_what_any_member_rejects(generator):
    models, test = _members(generator)
    step = BeliefMixture([models[0], _FlagsFirst(models[1])]).stream(len(test)).update(test[:, 0])
    assert step.rejected.tolist() == [j == 0 for j in range(len(test))]


def test_a_failing_member_leaves_every_stream_as_it_was(generator):
    # a shared transition takes any number of frames, a per-phase one only the training length
    # (5): the sixth frame fails in the second member after the first has taken it
    models, test = _members(generator)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        shared = LinearIDDM(phase=False).fit(models[0]._sequences, models[0].intentions[:, 0])
    stream = BeliefMixture([shared, models[1]]).stream(len(test))
    for t in range(5):
        stream.update(test[:, t])
    before = [(s.frames, s.log_weights.clone(), s.previous.clone()) for s in stream.streams]
    with pytest.raises(ValueError, match="no transition"):
        stream.update(test[:, 4] + 0.1)
    for s, (frames, log_w, previous) in zip(stream.streams, before, strict=True):
        assert s.frames == frames
        assert torch.equal(s.log_weights, log_w) and torch.equal(s.previous, previous)


def test_weights_as_arrays_and_extreme_values(generator):
    models, _ = _members(generator)
    assert BeliefMixture(models, weights=np.array([3.0, 1.0])).weights == [0.75, 0.25]
    assert BeliefMixture(models, weights=torch.tensor([1, 3])).weights == [0.25, 0.75]
    assert BeliefMixture(models, weights=[np.float32(1), np.float32(1)]).weights == [0.5, 0.5]
    # a sum that would overflow: still equal weights, no NaN
    assert BeliefMixture(models, weights=[1e308, 1e308]).weights == [0.5, 0.5]
    with pytest.raises(ValueError, match="weights"):
        BeliefMixture(models, weights=[10**400, 1])
    with pytest.raises(ValueError, match="weights"):
        BeliefMixture(models, weights=np.ones((2, 1)))


def test_rejects_bad_input(generator):
    models, test = _members(generator)
    with pytest.raises(TypeError, match="non-empty sequence"):
        BeliefMixture([])
    with pytest.raises(TypeError, match="no beliefs, stream, grid"):
        BeliefMixture([models[0], object()])
    for bad in ([1.0], [1.0, -1.0], [0.0, 0.0], [float("nan"), 1.0], [1.0, "a"]):
        with pytest.raises(ValueError, match="weights"):
            BeliefMixture(models, weights=bad)
    discrete, _ = _members(generator, discrete=True)
    with pytest.raises(ValueError, match="score different intention values"):
        BeliefMixture([models[0], discrete[0]])


def test_members_with_different_value_sets_raise_in_either_order(generator):
    # a 2-code and a 3-code member: before, the first order scored the 3-code member on codes
    # {0, 1} only (renormalising its belief there) while the other raised
    models, test = _members(generator, discrete=True)
    train, labels = models[0]._sequences, models[0].intentions[:, 0].long()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        two = LinearIDDM(intention="discrete").fit(train, labels.clamp(max=1))
    sets = {id(two): r"2 values \[0.0, 1.0\]", id(models[0]): r"3 values \[0.0, 1.0, 2.0\]"}
    for order in ([two, models[0]], [models[0], two]):
        match = (
            r"models\[0\] and models\[1\] score different intention values: "
            rf"models\[0\] {sets[id(order[0])]}, models\[1\] {sets[id(order[1])]}"
        )
        with pytest.raises(ValueError, match=match):
            BeliefMixture(order)
    # a continuous g over different ranges: different default grids, named by their range
    cont, _ = _members(generator)
    g = cont[0].intentions[:, 0]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        narrow = LinearIDDM().fit(cont[0]._sequences, 0.5 * g)
    for order in ([cont[0], narrow], [narrow, cont[0]]):
        with pytest.raises(ValueError, match=r"25 values over \[.*\], models\[1\] 25 values"):
            BeliefMixture(order)
    # the same value sets mix, in either order; a float32 member's rounded grid too
    BeliefMixture([models[1], models[0]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        single = LinearIDDM(dtype=torch.float32).fit(cont[0]._sequences, g)
    BeliefMixture([single, cont[0]])
    # a member without a default value set (a 2-D g) takes the grid it is given
    g2 = torch.stack([g, -g], 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flat = [LinearIDDM(coef_precision=1.0, noise_prior=0.1).fit(cont[0]._sequences, g2)] * 2
    grid = torch.tensor([[0.0, 0.0], [0.5, -0.5]])
    assert BeliefMixture(flat).beliefs(test, grid).prob.shape == (10, 5, 2)


def test_filter_beliefs_mix_a_gp_iddm_with_linear_models(generator):
    """FilterBeliefs gives the GP IDDM's online beliefs (the filter run frame by frame by hand)
    as a mixture member: the GP + linear mixture is the weighted average of the two."""
    from hgpdm_torch.inference import FilterBeliefs, OnlineIntentionFilter
    from hgpdm_torch.models import IDDM

    models, test = _members(generator)
    obs = torch.randn(12, 5, 2, generator=generator, dtype=torch.float64)
    grid = models[0].grid()  # the linear models' training range: the same default grid
    g = torch.linspace(float(grid.min()), float(grid.max()), 12, dtype=torch.float64)
    torch.manual_seed(0)
    gp = IDDM(list(obs), g, 2, intention="continuous", measurement="linear")
    member = FilterBeliefs(gp, forgetting=0.1)
    got = member.beliefs(test, grid)
    f = OnlineIntentionFilter(gp, grid, forgetting=0.1, batch_size=len(test))
    want = torch.stack([f.update(test[:, t]).log_prob for t in range(test.shape[1])], 1)
    # from_log renormalises an already normalised belief: a few ulp of log probs of order 10
    torch.testing.assert_close(got.log_prob, want, rtol=0, atol=1e-12)
    assert got.mean.shape == (len(test), test.shape[1], 1)
    mix = BeliefMixture([member, models[0]]).beliefs(test, grid)
    expected = 0.5 * got.prob + 0.5 * models[0].beliefs(test, grid).prob
    torch.testing.assert_close(mix.prob, expected, rtol=1e-12, atol=1e-15)
    # one stream, a log prior, and the options the member sets itself
    lp = torch.linspace(0, 1, len(grid), dtype=torch.float64)
    one = member.beliefs(test[0], grid, lp)
    f = OnlineIntentionFilter(gp, grid, forgetting=0.1, prior=lp.softmax(0))
    want = torch.stack([f.update(test[0, t]).log_prob for t in range(test.shape[1])])
    torch.testing.assert_close(one.log_prob, want, rtol=0, atol=1e-12)
    with pytest.raises(TypeError, match="sets \\['batch_size'\\] itself"):
        FilterBeliefs(gp, batch_size=3)
    with pytest.raises(TypeError, match="fitted HGPDM"):
        FilterBeliefs(models[0])
    with pytest.raises(ValueError, match="forgetting"):
        FilterBeliefs(gp, forgetting=2.0)


def test_one_belief_interface_and_one_streaming_protocol(generator):
    """Every model (LinearIDDM, a GP IDDM through FilterBeliefs, a mixture) is an
    IntentionModel and every stream (OnlineIntentionFilter, LinearIDDM's, a mixture's) an
    IntentionStream: one loop written against the protocol runs them all and gets the batch
    beliefs. The belief's entropy against scipy, its mixture against the weighted average."""
    from scipy import stats

    from hgpdm_torch.inference import (
        FilterBeliefs,
        IntentionBelief,
        IntentionModel,
        IntentionStream,
        OnlineIntentionFilter,
    )
    from hgpdm_torch.models import IDDM

    models, test = _members(generator)
    grid = models[0].grid()
    obs = torch.randn(12, 5, 2, generator=generator, dtype=torch.float64)
    g = torch.linspace(float(grid.min()), float(grid.max()), 12, dtype=torch.float64)
    torch.manual_seed(0)
    gp = IDDM(list(obs), g, 2, intention="continuous", measurement="linear")
    members = [models[0], FilterBeliefs(gp, forgetting=0.1)]
    members.append(BeliefMixture(members))
    assert isinstance(OnlineIntentionFilter(gp, grid), IntentionStream)

    def online(model: IntentionModel, z: torch.Tensor) -> torch.Tensor:
        stream = model.stream(len(z), grid)
        assert isinstance(stream, IntentionStream)
        return torch.stack([stream.update(z[:, t]).log_prob for t in range(z.shape[1])], 1)

    for model in members:
        assert isinstance(model, IntentionModel)
        batch = model.beliefs(test, grid)
        # the stream and the batch beliefs run the same updates: a few ulp of O(10) logs
        torch.testing.assert_close(online(model, test), batch.log_prob, rtol=0, atol=1e-10)
    assert not isinstance(object(), IntentionModel)

    belief = members[0].beliefs(test, grid)
    p = belief.prob.reshape(-1, len(grid)).numpy()
    torch.testing.assert_close(belief.entropy().reshape(-1), torch.as_tensor(stats.entropy(p.T)))
    certain = IntentionBelief.from_log(torch.tensor([0.0, -math.inf]), grid[:2], True)
    assert float(certain.entropy()) == 0.0
    parts = [m.beliefs(test, grid) for m in members[:2]]
    mixed = IntentionBelief.mixture(parts, [0.25, 0.75])
    torch.testing.assert_close(mixed.prob, 0.25 * parts[0].prob + 0.75 * parts[1].prob)
    torch.testing.assert_close(mixed.mean, 0.25 * parts[0].mean + 0.75 * parts[1].mean)
    with pytest.raises(ValueError, match="does not match"):
        IntentionBelief.mixture([parts[0], members[0].beliefs(test[0], grid)], [0.5, 0.5])
