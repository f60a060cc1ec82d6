"""The online filter's predictive step on the compiled kernel
(:mod:`hgpdm_torch.inference.intention.compiled`) against the same step in torch.

Both compute the same moments from the same GP weights, in other orders of summation: they
differ by the rounding of one filter step (``gp_rounding``: the solves with ``K + noise I`` that
made the weights bound how far any two evaluations of a step's moments may round apart, and the
kernel's sums over N^2 products of the contraction are well inside it). Where the kernel does not
run, the tests skip.
"""

from __future__ import annotations

import math

import pytest
import torch

from hgpdm_torch import native, settings
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.inference.intention.compiled import CompiledStep

pytestmark = pytest.mark.skipif(
    not native.available(),
    reason="the compiled kernel does not run here: it needs an x86-64 CPU with AVX-512F and DQ "
    "and a C compiler (native.available() is False)",
)

GRID = torch.linspace(-1.2, 1.2, 9)


def _state(model, B: int = 6, forgetting: float = 0.3, temperature: float = 1.5, grid=GRID):
    """A filter of B streams after two real frames each, and a third frame per stream (stream 1's
    missing: a NaN row), with log beliefs that differ between streams (stream 0 excludes three
    values: -inf)."""
    f = OnlineIntentionFilter(
        model, grid, batch_size=B, forgetting=forgetting, temperature=temperature
    )
    z = torch.stack([s[:3] for s in model.sequences()[:B]])
    for t in range(2):
        f.update(z[:, t])
    frame = z[:, 2].clone()
    frame[1] = math.nan
    gen = torch.Generator().manual_seed(0)
    log_belief = 3 * torch.randn(B, len(grid), generator=gen, dtype=torch.float64)
    log_belief[0, :3] = -math.inf
    log_belief = torch.log_softmax(log_belief, -1)
    return f, (f.mean.clone(), f.cov.clone(), log_belief, frame, None)


def _torch_step(f, args):
    step, f.compiled_step = f.compiled_step, None
    try:
        return f._step(*args)
    finally:
        f.compiled_step = step


@pytest.mark.parametrize(
    "forgetting, temperature, K",
    [(0.3, 1.5, 9), (0.0, 1.0, 9), (0.3, 1.5, 12), (0.3, 1.5, 14), (0.3, 1.5, 16)],
)
def test_step_equals_the_torch_step(continuous_iddm, gp_rounding, forgetting, temperature, K):
    """Means, covariances and beliefs of one step: the kernel's, the torch step on the kernel's
    contraction, and the materialised torch path, within one step's rounding of each one's
    scale (probabilities: of 1); the missing stream only forgets; excluded values stay
    excluded. K = 9, 12, 14 and 16 grid values: the contraction's last value or last four as dot
    products, six in a vector of eight, and whole vectors."""
    grid = torch.linspace(-1.2, 1.2, K)
    f, args = _state(continuous_iddm, forgetting=forgetting, temperature=temperature, grid=grid)
    got = f.compiled_step(*args)
    assert got is not None
    rel = gp_rounding(f.posterior, continuous_iddm.measurement_posterior())
    with settings.moment_path("materialised"):
        assert f.compiled_step(*args) is None  # the kernel runs on the fused path only
        references = [_torch_step(f, args)]
    references.append(_torch_step(f, args))
    for want in references:
        for a, b in zip(got[:2], want[:2], strict=True):
            torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))
        torch.testing.assert_close(got[2].exp(), want[2].exp(), rtol=rel, atol=rel)
    assert torch.isneginf(got[2][0, :3]).all() and torch.isfinite(got[2][0, 3:]).all()
    forgot = torch.log_softmax((1 - forgetting) * args[2][1], -1)
    torch.testing.assert_close(got[2][1], forgot, rtol=0, atol=8 * torch.finfo(torch.float64).eps)
    torch.testing.assert_close(got[0][1], references[1][0][1], rtol=0, atol=rel)


@pytest.mark.parametrize("inducing", [None, 40])
def test_filter_updates_match_with_and_without_the_kernel(continuous_iddm, gp_rounding, inducing):
    """Six updates of five streams, one frame missing, exact and sparse (DTC) transition GP:
    the filter with its compiled step and with the torch step agree to the rounding of one step
    per step taken."""
    z = torch.stack([s[:6] for s in continuous_iddm.sequences()[:5]])
    z[2, 3] = math.nan
    out = []
    for compiled in (True, False):
        f = OnlineIntentionFilter(
            continuous_iddm, GRID, batch_size=5, forgetting=0.2, inducing=inducing
        )
        assert f.compiled_step is not None
        if not compiled:
            f.compiled_step = None
        probs = torch.stack([f.update(z[:, t]).prob for t in range(6)])
        out.append((probs, f.mean.clone(), f.cov.clone()))
    rel = 6 * gp_rounding(f.posterior, continuous_iddm.measurement_posterior())
    for a, b in zip(*out, strict=True):
        torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))


def test_streams_are_independent_and_failures_go_to_torch(
    continuous_iddm, gp_rounding, monkeypatch
):
    """Each stream's results do not depend on the others in its call (to rounding: the quadratic
    forms come from batched torch linear algebra, which need not round alike in batches of
    other sizes on every machine); an innovation covariance
    that does not factorise (a negative measurement noise) sets its stream's status; where any
    status is set the step returns None and the filter's torch step takes the chunk (the same
    update as without the kernel)."""
    f, (m, P, lb, z, _) = _state(continuous_iddm)
    step = f.compiled_step
    trans = step.transition

    def call(rows, meas=step.meas):
        ops = trans.native_operands(m[rows], P[rows])
        return native.predictive_step(
            ops, trans.native_moment_terms, meas, step.rank, step.keep, step.temperature,
            z[rows].contiguous(), lb[rows].contiguous(),
        )  # fmt: skip

    *values, status = call(slice(None))
    keep = [0, 1, 3, 5]
    *alone, status_alone = call(keep)
    assert not status.any() and not status_alone.any()
    rel = gp_rounding(f.posterior)
    for a, b in zip(values, alone, strict=True):
        torch.testing.assert_close(a[keep], b, rtol=rel, atol=rel * float(b.abs().max()))
    bad = P.clone()
    bad[2] = math.nan  # not a covariance: the kernel's forms decline, torch's raise as before
    with pytest.raises(ValueError, match="NaN"):
        trans.native_operands(m, bad)
    negative = step.meas.clone()
    negative[-2] = -1e6  # the measurement noise: S = R P R^T + v I with v < 0
    assert call(slice(None), negative)[-1].tolist() == [1] * 6

    real = native.predictive_step

    def one_fails(*args):
        *out, status = real(*args)
        status[2] = 1
        return (*out, status)

    monkeypatch.setattr(native, "predictive_step", one_fails)
    assert step(m, P, lb, z, None) is None
    z_all = torch.stack([s[:4] for s in continuous_iddm.sequences()[:6]])
    filters = [OnlineIntentionFilter(continuous_iddm, GRID, batch_size=6) for _ in range(2)]
    filters[1].compiled_step = None
    for t in range(4):
        beliefs = [g.update(z_all[:, t]) for g in filters]
        assert torch.equal(beliefs[0].log_prob, beliefs[1].log_prob)


def test_built_only_where_it_can_run(continuous_iddm):
    """The bound evidence and the generic transition have no compiled step; with the kernels
    off, in float32 or under the debugging checks the step declines at call time."""
    assert OnlineIntentionFilter(continuous_iddm, GRID, evidence="bound").compiled_step is None
    generic = OnlineIntentionFilter(continuous_iddm, GRID, transition="generic")
    assert generic.compiled_step is None
    f, args = _state(continuous_iddm)
    assert isinstance(f.compiled_step, CompiledStep)
    with settings.native_kernels(False):
        assert f.compiled_step(*args) is None
    with settings.debug(True):  # the torch step checks its internal Gaussians
        assert f.compiled_step(*args) is None
    with settings.native_kernels(False):  # built with the kernels off: it runs once they are on
        later = OnlineIntentionFilter(continuous_iddm, GRID, batch_size=6)
    assert later.compiled_step(*args) is not None
    assert f.compiled_step(*(a.float() if a is not None else a for a in args)) is None


def test_inputs_are_checked(continuous_iddm):
    f, (m, P, lb, z, _) = _state(continuous_iddm)
    step, trans = f.compiled_step, f.compiled_step.transition
    ops = trans.native_operands(m, P)
    terms = trans.native_moment_terms
    with pytest.raises(ValueError, match="rank"):
        native.predictive_step(ops, terms, step.meas, 99, 0.8, 1.0, z, lb)
    with pytest.raises(ValueError, match="trans"):
        native.predictive_step(ops, terms[:-1].contiguous(), step.meas, step.rank, 0.8, 1.0, z, lb)
    with pytest.raises(ValueError, match="log_belief"):
        native.predictive_step(ops, terms, step.meas, step.rank, 0.8, 1.0, z, lb[:3].contiguous())
