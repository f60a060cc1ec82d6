"""Stream isolation of the online intention filter (issue 15).

One stream's bad observation (+-inf, partly NaN, 1e200, or merely implausible) or numerical
failure must not change any other stream's belief. The oracles are runs of the same filter
without the poison: the same 64 streams with the poisoned rows replaced by clean or missing
rows, and 63 streams without the poisoned last stream. Chunks of 9 streams divide 63, so the
63 other streams are updated in the same chunks in both runs; the comparisons are then exact
(float64, ``atol=1e-12``). (Different chunks round differently, and on this ill-conditioned
model, alpha-bar's process noise, rounding grows to ~1e-7 in the log belief within a few steps,
so a tolerance could not tell leakage from rounding.)
"""

from __future__ import annotations

import math

import pytest
import torch
from gpytorch.kernels import LinearKernel

from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.inference.filtering import ObservationCheck
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.linalg import CholeskyError

B, T, CHUNK = 64, 6, 9
LAST, MID = B - 1, 17  # MID sits inside the chunk [9, 18)
GRID = torch.linspace(-1.0, 1.0, 9)
STATE = ("mean", "cov", "log_belief")


@pytest.fixture(scope="module")
def model(continuous_iddm):
    return continuous_iddm


@pytest.fixture(scope="module")
def streams(model) -> torch.Tensor:
    """``[B, T, Dz]`` windows of the training movements, slightly perturbed."""
    seqs = model.sequences()
    z = torch.stack([seqs[b % len(seqs)][b % 4 : b % 4 + T] for b in range(B)])
    gen = torch.Generator().manual_seed(0)
    return z + 0.01 * torch.randn(z.shape, generator=gen, dtype=z.dtype)


@pytest.fixture(scope="module")
def clean(model, streams) -> dict[str, torch.Tensor]:
    return run(model, streams)[1]


@pytest.fixture(scope="module")
def fresh(model, streams) -> dict[int, dict[str, torch.Tensor]]:
    """Trajectories of streams started at step 3 and 4."""
    return {first: run(model, streams[:, first:])[1] for first in (3, 4)}


def run(model, z, poke=None, **options):
    """Filter ``z [S, T, Dz]``; ``poke(f, t)`` runs before update t. Returns the filter and the
    trajectories: state ``[S, T, ...]`` after each update and the flags ``[S, T]``."""
    f = OnlineIntentionFilter(model, GRID, batch_size=z.shape[0], chunk_size=CHUNK, **options)
    out = {key: [] for key in (*STATE, "rejected", "reset")}
    for t in range(z.shape[1]):
        if poke is not None:
            poke(f, t)
        belief = f.update(z[:, t])
        for key in STATE:
            out[key].append(getattr(f, key).clone())
        out["rejected"].append(belief.rejected.clone())
        out["reset"].append(belief.reset_streams.clone())
    return f, {key: torch.stack(v, 1) for key, v in out.items()}


def assert_same(a, b, rows, first=0):
    """Trajectories ``a`` from step ``first`` on equal ``b`` (from its step 0) in ``rows``."""
    for key in STATE:
        torch.testing.assert_close(
            a[key][rows, first:], b[key][rows, : T - first], rtol=0, atol=1e-12, msg=key
        )


def others(*streams):
    keep = torch.ones(B, dtype=torch.bool)
    keep[list(streams)] = False
    return keep


def poison_row(row: torch.Tensor, kind: str) -> torch.Tensor:
    row = row.clone()
    if kind == "partial NaN":
        row[2] = math.nan
    elif kind == "implausible":
        row[1] = 1e4  # finite and harmless to the arithmetic, but ~1e5 training sd out
    else:
        row[:] = {"1e200": 1e200, "+inf": math.inf, "-inf": -math.inf}[kind]
    return row


POISONED = [(LAST, 0), (LAST, 2), (LAST, 3), (MID, 4)]  # (stream, step); step 0 initialises


@pytest.mark.parametrize("kind", ["1e200", "+inf", "-inf", "partial NaN", "implausible"])
def test_bad_observation_is_rejected_for_its_stream_only(model, streams, clean, kind):
    bad, missing = streams.clone(), streams.clone()
    for b, t in POISONED:
        bad[b, t] = poison_row(streams[b, t], kind)
        missing[b, t] = math.nan
    f, poisoned = run(model, bad)
    _, as_missing = run(model, missing)
    _, without = run(model, bad[:LAST])

    # every other stream: as if the poison had not been there, at every step
    assert_same(poisoned, clean, others(LAST, MID))
    assert_same(poisoned, without, slice(0, LAST))  # MID included: it is isolated from LAST
    # the poisoned streams: exactly a missing observation (prediction-only step)
    assert_same(poisoned, as_missing, slice(None))
    flags = torch.zeros(B, T, dtype=torch.bool)
    for b, t in POISONED:
        flags[b, t] = True
    assert torch.equal(poisoned["rejected"], flags)
    assert not bool(poisoned["reset"].any())
    assert f.rejected_count.tolist() == [3 if b == LAST else int(b == MID) for b in range(B)]
    assert f.reset_count.sum() == 0 and bool(f.started.all())
    assert bool(torch.isfinite(poisoned["log_belief"]).all())


def test_single_stream_input_reports_scalar_flags(model, streams):
    f = OnlineIntentionFilter(model, GRID)
    assert f.update(streams[0, 0]).rejected.shape == ()
    out = f.update(torch.full_like(streams[0, 1], math.inf))
    assert out.prob.shape == (len(GRID),) and bool(out.rejected) and not bool(out.reset_streams)
    assert int(f.rejected_count[0]) == 1 and int(f.steps[0]) == 2


def _set(stream: int, key: str, value, at: int = 3):
    def poke(f, t):
        if t == at:
            getattr(f, key)[stream] = value

    return poke


@pytest.mark.parametrize(
    "how",
    [
        "huge mean",  # 1e200: the step overflows
        "CholeskyError",  # the shared transition raises for this stream (monkeypatched)
    ],
)
def test_numerical_failure_restarts_only_that_stream(model, streams, clean, fresh, how):
    value = {
        "huge mean": ("mean", 1e200),
        "CholeskyError": ("mean", 777.0),
    }[how]

    def poison(*targets):
        def poke(f, t):
            if how == "CholeskyError" and t == 0:
                moments = f.transition.moments

                def failing(m, P, phase=None, **options):
                    if bool((m == 777.0).any()):
                        raise CholeskyError("injected failure")
                    return moments(m, P, phase, **options)

                f.transition.moments = failing
                step = f.compiled_step  # the compiled kernel's whole step, where it runs
                if step is not None:

                    def failing_step(m, *rest):
                        if bool((m == 777.0).any()):
                            raise CholeskyError("injected failure")
                        return step(m, *rest)

                    f.compiled_step = failing_step
            for stream in targets:
                _set(stream, *value)(f, t)

        return poke

    f, poisoned = run(model, streams, poison(MID, LAST))
    _, without = run(model, streams[:LAST], poison(MID))
    # the others: as without the failure, at every step (the failing chunk is recomputed)
    assert_same(poisoned, clean, others(LAST, MID))
    assert_same(poisoned, without, slice(0, LAST))
    flags = torch.zeros(B, T, dtype=torch.bool)
    flags[[MID, LAST], 3] = True
    assert torch.equal(poisoned["reset"], flags), how
    assert not bool(poisoned["rejected"].any())
    assert f.reset_count.tolist() == [int(b in (MID, LAST)) for b in range(B)]
    # a failed stream is back at the prior after the failing update ...
    for stream in (MID, LAST):
        torch.testing.assert_close(poisoned["log_belief"][stream, 3], f.log_prior)
        torch.testing.assert_close(poisoned["mean"][stream, 3], f.mu0)
    # ... and restarts with its next observation like a new stream
    assert_same(poisoned, fresh[4], [MID, LAST], first=4)


def test_non_finite_state_restarts_with_the_current_observation(model, streams, clean, fresh):
    """A stored state that is not finite (set by hand) is restarted before the update; the stream
    then uses this update's observation as its first one."""

    def poke(f, t):
        _set(MID, "cov", math.nan)(f, t)
        _set(LAST, "log_belief", math.nan)(f, t)

    _, poisoned = run(model, streams, poke)
    assert_same(poisoned, clean, others(LAST, MID))
    assert_same(poisoned, fresh[3], [MID, LAST], first=3)
    assert poisoned["reset"][:, 3].nonzero().flatten().tolist() == [MID, LAST]


def test_the_normal_path_is_batched(model, streams):
    """One ``_step`` call per chunk of streams, however many streams are rejected, and a
    failure costs only the bisection of its own chunk."""
    f = OnlineIntentionFilter(model, GRID, batch_size=B, chunk_size=CHUNK)
    f.update(streams[:, 0])
    sizes = []
    step = f._step

    def counting(m, P, log_belief, z, phase):
        sizes.append(m.shape[0])
        return step(m, P, log_belief, z, phase)

    f._step = counting
    z = streams[:, 1].clone()
    z[::3] = math.inf
    f.update(z)
    assert sizes == [CHUNK] * 7 + [1]
    sizes.clear()
    f.mean[MID] = 1e200  # finite, so it passes the state check, but the step overflows
    f.update(streams[:, 2])
    assert len(sizes) <= 8 + 2 * math.ceil(math.log2(CHUNK)) + 2
    # the 6 other full chunks once, the failing one before and after its bisection
    assert sizes.count(CHUNK) == 8


def test_strict_raises_and_leaves_the_filter_unchanged(model, streams):
    f = OnlineIntentionFilter(model, GRID, batch_size=B, chunk_size=CHUNK, strict=True)
    f.update(streams[:, 0])
    f.update(streams[:, 1])
    before = {key: getattr(f, key).clone() for key in (*STATE, "started", "steps")}
    z = streams[:, 2].clone()
    z[MID, 4] = 1e200
    with pytest.raises(ValueError, match=rf"z\[{MID}\] \(stream {MID}, step 2\).*channel 4"):
        f.update(z)
    f.mean[LAST] = 1e200  # finite, so it passes the state check, but the step overflows
    before["mean"][LAST] = f.mean[LAST]
    with pytest.raises(ValueError, match=rf"stream {LAST} at step 2 failed numerically"):
        f.update(streams[:, 2])
    f.mean[LAST] = before["mean"][LAST] = f.mean[0]
    for bad in (torch.full_like(f.cov[LAST], math.nan), -10.0 * torch.eye(model.latent_dim)):
        f.cov[LAST] = before["cov"][LAST] = bad
        with pytest.raises(
            ValueError, match=rf"stream {LAST} at step 2 holds a non-finite or indefinite state"
        ):
            f.update(streams[:, 2])
    for key, value in before.items():
        torch.testing.assert_close(getattr(f, key), value, rtol=0, atol=0, equal_nan=True)
    assert f.rejected_count.sum() == 0 and f.reset_count.sum() == 0


def test_without_outlier_check_a_huge_value_fails_only_its_stream(model, streams):
    """``outlier_sd=None`` accepts 1e200; it overflows the update of its stream, which is then
    restarted, and the other streams are as without it."""
    bad = streams.clone()
    bad[MID, 2] = 1e200
    _, poisoned = run(model, bad, outlier_sd=None)
    _, clean = run(model, streams, outlier_sd=None)
    assert_same(poisoned, clean, others(MID))
    assert poisoned["reset"].nonzero().tolist() == [[MID, 2]]
    assert not bool(poisoned["rejected"].any())


# ----- the threshold -------------------------------------------------------------------------


def test_threshold_is_in_training_standard_deviations(model):
    f = OnlineIntentionFilter(model, GRID, batch_size=4)
    check = f.check
    z = model.observations
    torch.testing.assert_close(check.center, z.mean(0))
    meas = model.measurement_posterior()
    noise = meas.noise * meas.scale**2
    torch.testing.assert_close(check.spread, (z.var(0, correction=0) + noise).sqrt())
    rows = check.center.repeat(4, 1)
    rows[0, 1] += 99.0 * check.spread[1]
    rows[1, 1] -= 101.0 * check.spread[1]
    rows[2, 3] += 101.0 * check.spread[3]
    assert check.classify(rows)[1].tolist() == [False, True, True, False]
    assert f.update(rows).rejected.tolist() == [False, True, True, False]
    loose = OnlineIntentionFilter(model, GRID, batch_size=4, outlier_sd=200)
    assert not bool(loose.update(rows).rejected.any())


def test_threshold_is_relative_to_each_channel(generator):
    """Rescaling and shifting a channel in the training and test data alike changes nothing; a
    channel constant in training accepts values within ``outlier_sd`` noise deviations."""
    x = torch.randn(40, 2, generator=generator)
    y = x @ torch.randn(2, 3, generator=generator)
    y[:, 2] = 0.0  # constant channel
    post = GPPosterior(LinearKernel(), x, y, 0.1)
    a = 1000.0
    unit = torch.tensor([a, 1.0, 1.0])
    scaled = GPPosterior(
        LinearKernel(), x, y * unit, 0.1, scale=unit, offset=torch.tensor([5.0, 0, 0])
    )
    z = 5.0 * torch.randn(200, 3, generator=generator) * y.std(0).clamp_min(0.3)
    z[:10] *= 40.0
    _, bad = ObservationCheck.from_measurement(post).classify(z)
    _, bad_scaled = ObservationCheck.from_measurement(scaled).classify(
        z * unit + torch.tensor([5.0, 0, 0])
    )
    assert torch.equal(bad, bad_scaled)
    assert int(bad[:10].sum()) >= 5 and not bool(bad[10:].any())
    constant = torch.zeros(2, 3)
    constant[0, 2] = 99.0 * 0.1**0.5
    constant[1, 2] = 101.0 * 0.1**0.5
    assert ObservationCheck.from_measurement(post).classify(constant)[1].tolist() == [False, True]
    with pytest.raises(ValueError, match="outlier_sd"):
        ObservationCheck.from_measurement(post, 0.0)
    with pytest.raises(TypeError, match="outlier_sd"):
        ObservationCheck.from_measurement(post, "100")


def test_indefinite_state_restarts_its_stream(model, streams, clean, fresh):
    """A stored covariance with a clearly negative eigenvalue but finite entries (which the
    moment matching of a linear measurement would carry on with) restarts its stream like a
    non-finite one, with ``settings.debug`` off."""
    bad = torch.eye(model.latent_dim, dtype=streams.dtype)
    bad[-1, -1] = -0.05
    _, poisoned = run(model, streams, _set(MID, "cov", bad))
    assert_same(poisoned, clean, others(MID))
    assert_same(poisoned, fresh[3], [MID], first=3)
    assert poisoned["reset"][:, 3].nonzero().flatten().tolist() == [MID]


# ----- LinearIDDM streams: the same rule, through the same code ------------------------------

LINEAR_B, LINEAR_T = 8, 5
LINEAR_POISONED = [(7, 0), (7, 2), (3, 3)]  # (stream, frame)


def _linear_model(generator, **options):
    """A LinearIDDM with forgetting and a temperature (both parts of the recursion run), and 8
    held-out ``[T, Dz]`` streams."""
    from hgpdm_torch.models import LinearIDDM

    n = 60
    g = 2 * torch.rand(n, generator=generator) - 1
    z = [torch.randn(n, 4, generator=generator)]
    for _ in range(LINEAR_T - 1):
        z.append(0.8 * z[-1] + 0.5 * g[:, None] + 0.3 * torch.randn(n, 4, generator=generator))
    obs = torch.stack(z, 1)
    model = LinearIDDM(noise="diagonal", coef_precision=1.0, noise_prior=0.1, forgetting=0.2,
                       temperature=1.5, **options).fit(obs[:50], g[:50])  # fmt: skip
    return model, obs[50 : 50 + LINEAR_B]


def _linear_run(model, z, **options):
    """``model.stream`` over ``z [S, T, Dz]``: the stream and its log weights ``[S, T, K]`` and
    flags ``[S, T]`` after each frame."""
    stream = model.stream(z.shape[0], **options)
    weights, flags = [], []
    for t in range(z.shape[1]):
        belief = stream.update(z[:, t])
        weights.append(stream.log_weights.clone())
        flags.append(belief.rejected.clone())
    return stream, torch.stack(weights, 1), torch.stack(flags, 1)


@pytest.mark.parametrize("kind", ["1e200", "+inf", "-inf", "partial NaN", "implausible"])
def test_linear_iddm_stream_rejects_a_bad_row_for_its_stream_only(generator, kind):
    """As the online filter: the bad row is rejected and flagged, its stream takes it as a
    missing frame (no evidence into or out of it; it forgets), and every other stream's belief
    is as without it, bit for bit. Before, a 1e200 row left its stream NaN until reset()."""
    model, z = _linear_model(generator)
    bad, missing = z.clone(), z.clone()
    for b, t in LINEAR_POISONED:
        bad[b, t] = poison_row(z[b, t], kind)
        missing[b, t] = math.nan
    stream, poisoned, flags = _linear_run(model, bad)
    _, clean, _ = _linear_run(model, z)
    _, as_missing, missing_flags = _linear_run(model, missing)
    keep = [b for b in range(LINEAR_B) if b not in (3, 7)]
    assert torch.equal(poisoned[keep], clean[keep])
    assert torch.equal(poisoned, as_missing)
    assert not torch.equal(poisoned[3], clean[3]) and not torch.equal(poisoned[7], clean[7])
    expected = torch.zeros(LINEAR_B, LINEAR_T, dtype=torch.bool)
    for b, t in LINEAR_POISONED:
        expected[b, t] = True
    assert torch.equal(flags, expected)
    assert not bool(missing_flags.any())  # a row of NaN is missing, not rejected
    assert stream.rejected_count.tolist() == [2 if b == 7 else int(b == 3) for b in range(8)]
    assert bool(torch.isfinite(poisoned).all())


def test_linear_iddm_stream_strict_and_without_the_threshold(generator):
    model, z = _linear_model(generator)
    stream = model.stream(LINEAR_B, strict=True)
    for t in range(2):
        stream.update(z[:, t])
    keys = ("log_weights", "previous", "has_previous", "rejected_count")
    before = {key: getattr(stream, key).clone() for key in keys}
    row = z[:, 2].clone()
    row[3, 1] = 1e200
    with pytest.raises(ValueError, match=r"z\[3\] \(stream 3, frame 2\) cannot be used: channel 1"):
        stream.update(row)
    assert stream.frames == 2
    assert all(torch.equal(getattr(stream, key), value) for key, value in before.items())
    # outlier_sd=None takes any finite row; one whose transition overflows is rejected for its
    # stream alone (strict: raised), never NaN
    loose, _ = _linear_model(torch.Generator().manual_seed(1234), outlier_sd=None)
    bad, missing = z.clone(), z.clone()
    bad[3, 2], missing[3, 2] = 1e200, math.nan
    _, poisoned, flags = _linear_run(loose, bad)
    _, clean, _ = _linear_run(loose, z)
    _, as_missing, _ = _linear_run(loose, missing)
    keep = [b for b in range(LINEAR_B) if b != 3]
    assert torch.equal(poisoned[keep], clean[keep]) and torch.equal(poisoned, as_missing)
    assert flags.nonzero().tolist() == [[3, 2]]
    strict = loose.stream(LINEAR_B, strict=True)
    for t in range(2):
        strict.update(z[:, t])
    with pytest.raises(ValueError, match=r"z\[3\] \(stream 3, frame 2\).* not finite"):
        strict.update(bad[:, 2])


def test_every_online_belief_screens_rows_through_one_function(model, streams, monkeypatch):
    """The online filter and the LinearIDDM stream check and reject rows in one place."""
    from hgpdm_torch import observations
    from hgpdm_torch.inference.intention import streams as gp_streams
    from hgpdm_torch.models import linear_iddm_stream

    screen = observations.screen_observations
    users = (gp_streams, linear_iddm_stream)
    assert all(module.screen_observations is screen for module in users)
    linear, z = _linear_model(torch.Generator().manual_seed(0))
    calls = []

    def counting(*args, **kwargs):
        calls.append(args[1])  # the ObservationCheck
        return screen(*args, **kwargs)

    for module in users:
        monkeypatch.setattr(module, "screen_observations", counting)
    OnlineIntentionFilter(model, GRID).update(streams[0, 0])
    linear.stream(LINEAR_B).update(z[:, 0])
    assert [type(check) for check in calls] == [ObservationCheck, ObservationCheck]
