"""The fused psi2 path (:mod:`hgpdm_torch.tiling`, ``settings.moment_path("fused")``) against the
materialised one it replaces, in every place the same algebra runs: the IDDM's shared
transition, the generic moment matching (:func:`hgpdm_torch.moments.input_moments`: GP-ADF, VB,
MAP), the online filter and the Monte-Carlo planner; gradients, memory, the operation counts.

Tolerances. Both paths compute each entry of ``psi2`` from the same exponent, then contract it
with the same weights in another order (tile by tile, groups before rows, the centring after
instead of before the contraction); the exponentials may come from NumPy instead of torch
(``tiling.exp_``: each within an ulp or two of the exact value). Every moment is a sum over
``N^2`` entries weighted by ``beta = (K + noise I)^-1 Y``, so the two differ by the rounding of
such sums relative to the moment's scale: ``N eps cond(K + noise I)``, the ``gp_rounding`` of the
posterior (tests/conftest.py), which also bounds the shared against the generic path.
"""

from __future__ import annotations

import copy

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

import hgpdm_torch.gp_shared as gp_shared
from benchmarks._common import peak_bytes
from hgpdm_torch import native, settings, tiling
from hgpdm_torch.expectations import kernel_leaves, split_terms
from hgpdm_torch.gp import GPPosterior
from hgpdm_torch.gp_shared import SharedTransition
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.kernels import transition_kernel
from hgpdm_torch.moments import input_moments, input_operations, pair_operations
from hgpdm_torch.tiling import (
    CPU_STREAM_CHUNK,
    NATIVE_STREAM_CHUNK,
    OpCount,
    exp_,
    per_tile,
    stream_chunk,
)

from .conftest import EPS
from .test_gp_gaussian import KINDS, known_g, make_posterior

DX = 3


def _close(got, want, rel: float) -> None:
    """Each tensor within ``rel`` of its own scale (entries of a covariance carry the rounding
    of the whole matrix)."""
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))


def _iddm_posterior(kind: str, gen: torch.Generator) -> tuple[GPPosterior, torch.Tensor]:
    """An IDDM-style transition GP over ``[x, g]``, unequal groups of equal g, and a grid."""
    n_seq, per = 10, 4
    kernel = transition_kernel(kind, DX, num_values=4, alpha=(0.9, 0.4, 0.1, 1e-2))
    X = torch.randn(n_seq * per, DX, generator=gen)
    if kind == "iddm_continuous":
        g_seq = torch.rand(n_seq, generator=gen) * 2 - 1
        values = torch.linspace(-1.2, 1.2, 5)[:, None]
    else:
        g_seq = (torch.arange(n_seq) % 4).double()
        values = torch.tensor([[2.0], [0.0], [3.0]])
    G = g_seq.repeat_interleave(per)[:, None]
    keep = torch.ones(len(X), dtype=torch.bool)
    keep[[1, 6, 7]] = False  # unequal groups exercise the padding
    X, G = X[keep], G[keep]
    return GPPosterior(kernel, torch.cat([X, G], 1), torch.tanh(X) + 0.3 * G, 1e-2), values


def _gaussians(b: int, d: int, gen: torch.Generator, scale: float = 0.1):
    mu = torch.randn(b, d, generator=gen)
    A = torch.randn(b, d, d, generator=gen)
    return mu, scale * A @ A.mT + 1e-3 * torch.eye(d)


@pytest.mark.parametrize("numpy_exp", [True, False])
def test_exp_matches_torch(numpy_exp, monkeypatch):
    """NumPy's exponential where it is the faster one, torch's otherwise (both branches, whatever
    this machine picks): within two ulps of torch's (each is within about one of the exact
    value), inf on overflow, 0 on underflow, no warning (below the smallest normal number,
    subnormal results may be rounded or flushed differently: an absolute ``tiny``); a tensor
    that needs a gradient keeps torch's."""
    monkeypatch.setattr(tiling, "_numpy_is_faster", lambda dtype: numpy_exp)
    for dtype in (torch.float64, torch.float32):
        x = torch.linspace(-800.0, 800.0, 100_001, dtype=dtype)
        want = torch.exp(x)
        with settings.native_kernels(False):  # the compiled one: tests/test_native.py
            got = exp_(x.clone())
        ulp = 2 * torch.finfo(dtype).eps
        finite = torch.isfinite(want)
        tiny = torch.finfo(dtype).tiny
        torch.testing.assert_close(got[finite], want[finite], rtol=ulp, atol=tiny)
        assert torch.equal(torch.isinf(got), torch.isinf(want)) and bool(torch.isinf(got).any())
    leaf = torch.zeros(3, requires_grad=True)
    out = exp_(leaf.clone())
    out.sum().backward()
    assert torch.equal(leaf.grad, torch.ones(3))


@pytest.mark.parametrize("kind", ["iddm_continuous", "iddm_discrete"])
@pytest.mark.parametrize("streams_per_tile", [1, 3, None, "native"])
def test_shared_transition_fused_equals_materialised(
    kind, streams_per_tile, generator, gp_rounding
):
    """Tiles of 1 stream, of 3 (the last one short) and of all 7 give the materialised moments,
    and so does the compiled kernel (:mod:`hgpdm_torch.native`) where it runs."""
    if streams_per_tile == "native" and not native.available():
        pytest.skip("the compiled kernel does not run here (native.available() is False)")
    post, values = _iddm_posterior(kind, generator)
    fast = SharedTransition(post, values)
    mu, S = _gaussians(7, DX, generator)
    with settings.moment_path("materialised"):
        want = fast.moments(mu, S)
    with settings.native_kernels(streams_per_tile == "native"):
        if isinstance(streams_per_tile, int):
            with settings.tile_bytes(streams_per_tile * fast.workspace() * 8):
                got = fast.moments(mu, S)
        else:
            got = fast.moments(mu, S)
    _close(got, want, gp_rounding(post))


@pytest.mark.parametrize("kind", KINDS)
def test_generic_moments_fused_equal_materialised(kind, generator, gp_rounding):
    """predict_gaussian for 6 streams x 4 intentions (the filter's generic transition) in tiles
    of one stream, and the VB free energy's diagonal second moments without ``K^-1``."""
    gp = make_posterior(kind, generator)
    mu, S = _gaussians(6, 2, generator)
    g = known_g(kind, generator, (1, 4))
    args = (mu[:, None], S[:, None])
    with settings.moment_path("materialised"):
        want = gp.predict_gaussian(*args, g=g, include_noise=True)
    with settings.tile_bytes(1):  # one input Gaussian per tile
        got = gp.predict_gaussian(*args, g=g, include_noise=True)
    _close(got, want, gp_rounding(gp))
    leaves = kernel_leaves(gp.kernel, gp.input_dim)
    X = gp.train_inputs
    gk = None if g is None else g.expand(6, 4, 1)
    if "discrete" in kind:
        return  # codes never enter the VB diagonal form on their own (blocks do; above)
    terms = split_terms(leaves, X, gk, 2)
    diag = []
    for path in ("materialised", "fused"):
        with settings.moment_path(path), settings.tile_bytes(1):
            m, s2, tr, grad = input_moments(
                terms, *args, X[..., :2], gp.weights, None, diagonal=True, grad=False
            )
            assert tr is None and grad is None
            diag.append((m, s2))
    _close(diag[1], diag[0], gp_rounding(gp))


@pytest.mark.parametrize("recompute", [True, False])
def test_fused_paths_have_gradients(generator, monkeypatch, recompute):
    """gradcheck through tiles of one input Gaussian, each recomputed in the backward pass
    (torch.utils.checkpoint) or kept for it: the shared transition and the generic moments."""
    if recompute:
        monkeypatch.setattr(tiling, "KEEP_FOR_BACKWARD_BYTES", 0)
    post, values = _iddm_posterior("iddm_continuous", generator)
    fast = SharedTransition(post, values)
    mu0, S0 = _gaussians(2, DX, generator)
    A0 = torch.linalg.cholesky(S0)

    def shared(mu, A):
        return fast.moments(mu, A @ A.mT)

    gp = make_posterior("continuous", generator, N=8)
    g = torch.tensor([[0.3], [-0.5]])

    def generic(mu, A):
        return gp.predict_gaussian(mu[:, None], (A @ A.mT)[:, None], g=g, include_noise=True)

    with settings.tile_bytes(1):
        for fn, mu in ((shared, mu0), (generic, mu0[:, :2])):
            A = A0[:, : mu.shape[1], : mu.shape[1]].clone().requires_grad_(True)
            assert torch.autograd.gradcheck(fn, (mu.clone().requires_grad_(True), A))


def test_fused_memory_per_stream_is_not_psi2(generator):
    """Each more stream costs the materialised shared transition at least its ``N x N``
    ``psi2``, the fused one (tiles of one stream) less than a quarter of it: what a stream holds
    there is O(N (Dx + K)); the tile is allocated once."""
    kernel = transition_kernel("iddm_continuous", DX, alpha=(0.9, 0.4, 0.1, 1e-2))
    X = torch.randn(160, DX, generator=generator)
    G = torch.linspace(-1, 1, 32).repeat_interleave(5)[:, None]
    post = GPPosterior(kernel, torch.cat([X, G], 1), torch.tanh(X), 1e-2)
    fast = SharedTransition(post, torch.linspace(-1, 1, 5)[:, None])
    n, cpu = fast.inputs.shape[0], torch.device("cpu")
    growth = {}
    for path in ("materialised", "fused"):
        with settings.moment_path(path), settings.tile_bytes(fast.workspace() * 8):
            peaks = [
                peak_bytes(lambda b=b: fast.moments(*_gaussians(b, DX, generator)), cpu)
                for b in (16, 64)
            ]
        growth[path] = (peaks[1] - peaks[0]) / 48  # bytes per additional stream
    psi2 = n * n * 8
    assert growth["materialised"] >= psi2 > 4 * growth["fused"]


def test_filter_agrees_across_paths(continuous_iddm, gp_rounding):
    """Beliefs of 5 streams over 6 steps on both paths: the same to the rounding of one step per
    step taken (the planner's particles: tests/decision/test_mcp.py)."""
    model = continuous_iddm
    grid = torch.linspace(-1.2, 1.2, 9)
    z = torch.stack([s[:6] for s in model.sequences()[:5]])
    out = {}
    paths = [("materialised", False), ("fused", False)]
    if native.available():  # the compiled kernel (hgpdm_torch.native), the default where it runs
        paths.append(("fused", True))
    for path, compiled in paths:
        with settings.moment_path(path), settings.native_kernels(compiled):
            f = OnlineIntentionFilter(model, grid, batch_size=5, forgetting=0.2)
            probs = [f.update(z[:, t]).prob for t in range(6)]
            out[path, compiled] = (torch.stack(probs), f.mean.clone(), f.cov.clone())
    rel = 6 * gp_rounding(f.posterior, model.measurement_posterior())
    for key in paths[1:]:
        _close(out[key], out["materialised", False], rel)


def test_stream_chunk_per_path_and_device():
    cpu = torch.device("cpu")
    n = 500
    assert stream_chunk(n, 3 * n * n, torch.float64, cpu) == CPU_STREAM_CHUNK
    assert stream_chunk(n, 3 * n * n, torch.float64, cpu, compiled=True) == NATIVE_STREAM_CHUNK
    with settings.moment_path("materialised"):
        assert stream_chunk(n, 3 * n * n, torch.float64, cpu) == 2**19 // (n * n)
    with settings.tile_bytes(10 * 8 * n * n):
        assert per_tile(n * n, torch.float64, cpu) == 10
        assert per_tile(n * n, torch.float32, cpu) == 20
    with pytest.raises(ValueError, match="path"):
        settings.moment_path("fast")
    with pytest.raises(ValueError, match="size"):
        settings.tile_bytes(0)


def test_operation_counts_cover_the_work(generator, monkeypatch):
    """The floor's counts against independent ones: the exponentials the shared transition
    takes (counted at ``tiling.exp_``) and the multiply-adds of its matrix products
    (``torch.utils.flop_counter``), which are most of its work; and the generic pair's."""
    post, values = _iddm_posterior("iddm_continuous", generator)
    fast = SharedTransition(post, values)
    mu, S = _gaussians(4, DX, generator)
    taken = []

    def counting_exp(t):
        taken.append(t.numel())
        return exp_(t)

    monkeypatch.setattr(gp_shared, "exp_", counting_exp)
    with settings.native_kernels(False), FlopCounterMode(display=False) as counter:
        fast.moments(mu, S)
        count = fast.operations()
    n = fast.inputs.shape[0]
    assert sum(taken) == 4 * n * n == 4 * (count.exps - n)
    products = counter.get_total_flops() / 2 / 4  # multiply-adds per stream
    assert 0.8 * count.madds < products < count.madds
    # without Cov[x, f] (the predictive filter, the planner): the same mean and covariance,
    # and the count and the products both lose the expected gradient's work
    with settings.native_kernels(False), FlopCounterMode(display=False) as counter:
        mean, cov, cross = fast.moments(mu, S, cross=False)
        lean = fast.operations(cross=False)
    with settings.native_kernels(False):
        full = fast.moments(mu, S)
    assert cross is None and torch.equal(mean, full[0]) and torch.equal(cov, full[1])
    fewer = counter.get_total_flops() / 2 / 4
    assert lean.exps == count.exps and 0.8 * lean.madds < fewer < lean.madds < count.madds
    # the count's difference has the expected gradient's triangular solve too, which the flop
    # counter does not see (measured 1.5 times the products' difference)
    assert products - fewer < count.madds - lean.madds < 2 * (products - fewer)
    if native.available():  # the compiled kernel's own algebra: fewer multiply-adds
        with FlopCounterMode(display=False) as counter:
            fast.moments(mu, S)
        ours = fast.operations()
        assert ours.exps == count.exps and ours.madds < count.madds
        assert counter.get_total_flops() / 2 / 4 < 0.2 * ours.madds  # the rest is in C
    # the generic path (predict_gaussian, K values sharing each input, the IDDM's one RBF
    # term): the call's count against the matrix products it runs, most of its work
    k, generic = len(values), make_posterior("iddm_continuous", torch.Generator().manual_seed(0))
    g = torch.linspace(-1, 1, k)[None, :, None]
    mu2, S2 = _gaussians(4, 2, generator)
    with FlopCounterMode(display=False) as counter:
        generic.predict_gaussian(mu2[:, None], S2[:, None], g=g, include_noise=True)
    N, X = generic.train_inputs.shape[0], generic.train_inputs
    terms = split_terms(kernel_leaves(generic.kernel, 3), X, g[0], 2)
    count = input_operations(terms, N, 2, sets=k, inputs=4)
    assert count.exps == N * N + N and pair_operations(N, 2, 2, sets=k).exps == N * N
    assert 0.8 * count.madds < counter.get_total_flops() / 2 / 4 < count.madds
    assert (OpCount(1.0, 2.0) * 3 + OpCount(1.0, 0.0)).seconds(4.0, 2.0) == 1.0 + 3.0


def test_tile_rounding_is_independent_of_neighbours(generator):
    """A stream's fused moments do not depend on which other streams share its tiles beyond
    rounding: each stream alone, or in tiles of 2, of 5 and all together (bit for bit is not
    promised across tile sizes: other batch shapes may take other BLAS kernels)."""
    post, values = _iddm_posterior("iddm_discrete", generator)
    fast = SharedTransition(post, values)
    mu, S = _gaussians(5, DX, generator)
    alone = [fast.moments(mu[i : i + 1], S[i : i + 1]) for i in range(5)]
    alone = [torch.cat([a[j] for a in alone]) for j in range(3)]
    for per in (2, 5):
        with settings.tile_bytes(per * fast.workspace() * 8):
            together = fast.moments(mu, S)
        n = fast.inputs.shape[0]
        _close(together, alone, 4 * n * EPS * float(torch.linalg.cond(post.kinv)))


def test_gradients_through_a_posterior_that_keeps_its_graph(generator, gp_rounding):
    """A posterior with ``detach=False`` whose kernel is trained (its weights and ``K^-1`` need
    gradients, the inputs do not): the fused shared transition takes its differentiable tiles,
    and the gradient of the kernel's parameters is the materialised path's, to the rounding of
    the gradient's sums through ``K^-1`` (``gp_rounding`` of its scale)."""
    post, values = _iddm_posterior("iddm_continuous", generator)
    kernel = copy.deepcopy(post.kernel).requires_grad_(True)
    live = GPPosterior(kernel, post.train_inputs, post.train_targets, post.noise, detach=False)
    mu, S = _gaussians(3, DX, generator)
    grads = []
    for path in ("materialised", "fused"):
        with settings.moment_path(path):
            fast = SharedTransition(live, values)
            assert fast.beta_rows.requires_grad  # the case: only the GP's side needs gradients
            mean, cov, _ = fast.moments(mu, S)
            grads.append(torch.autograd.grad(mean.sum() + cov.sum(), list(kernel.parameters())))
    rel = gp_rounding(post)
    for a, b in zip(grads[1], grads[0], strict=True):
        torch.testing.assert_close(a, b, rtol=rel, atol=rel * float(b.abs().max()))


def _phase_transition(generator) -> tuple[GPPosterior, SharedTransition]:
    """A phase-aware shared transition (its phase factor in psi2's exponent)."""
    kernel = transition_kernel("iddm_continuous", DX, alpha=(0.9, 0.4, 0.1, 1e-2),
                               phase_width=1.5)  # fmt: skip
    X = torch.randn(24, DX, generator=generator)
    G = torch.linspace(-1, 1, 6).repeat_interleave(4)[:, None]
    p = torch.arange(4.0).repeat(6)[:, None]
    post = GPPosterior(kernel, torch.cat([X, G, p], 1), torch.tanh(X), 1e-2)
    return post, SharedTransition(post, torch.linspace(-1, 1, 3)[:, None], phase=True)


@pytest.mark.parametrize("path", ["tiles", "native"])
def test_phase_paths_equal_materialised(path, generator, gp_rounding):
    """With a phase factor per point and stream, the torch tiles and the compiled kernel (which
    adds the log factors to its own exponent) give the materialised moments."""
    if path == "native" and not native.available():
        pytest.skip("the compiled kernel does not run here (native.available() is False)")
    post, fast = _phase_transition(generator)
    mu, S = _gaussians(3, DX, generator)
    phase = torch.tensor([0.0, 2.0, 3.5])
    with settings.moment_path("materialised"):
        want = fast.moments(mu, S, phase)
    with settings.native_kernels(path == "native"), torch.no_grad():
        got = fast.moments(mu, S, phase)
    _close(got, want, gp_rounding(post))


def test_phase_path_has_gradients(generator, monkeypatch):
    """gradcheck of a phase-aware shared transition (its phase factor in the exponent) in tiles
    of one stream, recomputed in the backward pass."""
    monkeypatch.setattr(tiling, "KEEP_FOR_BACKWARD_BYTES", 0)
    _, fast = _phase_transition(generator)
    mu0, S0 = _gaussians(2, DX, generator)
    phase = torch.tensor([0.0, 2.0])

    def f(mu, A):
        return fast.moments(mu, A @ A.mT, phase)

    A = torch.linalg.cholesky(S0).requires_grad_(True)
    with settings.tile_bytes(1):
        assert torch.autograd.gradcheck(f, (mu0.clone().requires_grad_(True), A))


def test_tiles_stay_in_budget_with_two_batch_dims(generator, gp_rounding):
    """Input Gaussians that differ along two batch dims (streams x intentions, as in a GP-ADF
    step over all K): tiles of one input each, the moments of the materialised path, and a peak
    allocation under a fifth of the materialised one."""
    gp = make_posterior("continuous", generator, N=150)
    mu = torch.randn(6, 5, 2, generator=generator)
    A = 0.3 * torch.randn(6, 5, 2, 2, generator=generator)
    S = A @ A.mT + 0.01 * torch.eye(2)
    g = torch.randn(1, 5, 1, generator=generator)
    with settings.moment_path("materialised"):
        want = gp.predict_gaussian(mu, S, g=g)
        big = peak_bytes(lambda: gp.predict_gaussian(mu, S, g=g), torch.device("cpu"))
    n = gp.train_inputs.shape[0]
    with settings.tile_bytes(n * n * 8):
        got = gp.predict_gaussian(mu, S, g=g)
        small = peak_bytes(lambda: gp.predict_gaussian(mu, S, g=g), torch.device("cpu"))
    _close(got, want, gp_rounding(gp))
    # what is left is O(N D) per input (psi1, the exponent's factors), not 30 N^2
    assert small < big / 5


def test_no_streams(generator):
    post, values = _iddm_posterior("iddm_continuous", generator)
    mu, S = _gaussians(0, DX, generator)
    mean, cov, cross = SharedTransition(post, values).moments(mu, S)
    assert mean.shape == (0, len(values), DX) and cov.shape == (0, len(values), DX, DX)
