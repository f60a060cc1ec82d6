"""The compiled CPU kernel (:mod:`hgpdm_torch.native`) against independent references.

- its exponential against mpmath at 200 bits (within 2 ulp; 0, inf and NaN where IEEE-754 puts
  them), its categorical and normal draws against torch's (and mpmath's Box-Muller values of
  torch's uniforms);
- its group sums of ``psi2 = exp(left @ right)`` against the dense formulas in torch, within a
  first-order rounding bound of both (the exponent's products, the exponential, the sums);
- one warning and the torch path where no compiler is found or the build fails;
- a build into an empty cache folder, threads with their own buffers, and its inputs' checks.

Where the kernel cannot run (no AVX-512F and DQ, no compiler) the tests that need it skip; the
fallback tests run everywhere.
"""

from __future__ import annotations

import math
import shutil
import stat
import threading
import warnings

import mpmath
import pytest
import torch

from hgpdm_torch import native, settings
from hgpdm_torch.gp_shared import SharedTransition

from .conftest import EPS
from .test_tiling import DX, _close, _gaussians, _iddm_posterior

needs_kernel = pytest.mark.skipif(
    not native.available(),
    reason="the compiled kernel does not run here: it needs an x86-64 CPU with AVX-512F and DQ "
    "and a C compiler (native.available() is False)",
)


@needs_kernel
def test_exp_within_two_ulp_of_the_exact_value():
    """Random points over the whole finite range, near 0, and the edges of overflow and
    underflow: within 2 ulp of the exact value (subnormal results: 2 ulp of the smallest
    subnormal, as the result is rounded twice), inf and 0 beyond the range."""
    gen = torch.Generator().manual_seed(0)
    x = torch.cat(
        [
            torch.empty(3000, dtype=torch.float64).uniform_(-746.0, 710.0, generator=gen),
            torch.empty(1000, dtype=torch.float64).uniform_(-1.0, 1.0, generator=gen),
            torch.linspace(-40.0, 40.0, 1001, dtype=torch.float64),
            torch.tensor([0.0, -0.0, 5e-324, -1e-300, 709.78, 709.783, -708.39, -708.4]),
            torch.tensor([-745.13, -745.14, -746.0, 710.0, 1e308, -1e308]),
        ]
    )
    got = native.exp_(x.clone()).tolist()
    mpmath.mp.prec = 200
    top, tiny = torch.finfo(torch.float64).max, torch.finfo(torch.float64).tiny
    for v, g in zip(x.tolist(), got, strict=True):
        exact = mpmath.exp(mpmath.mpf(v))
        if exact > top:
            assert g == math.inf, v
        elif exact >= tiny:
            assert abs(mpmath.mpf(g) - exact) <= 2 * math.ulp(float(exact)), v
        else:
            assert abs(mpmath.mpf(g) - exact) <= 2 * 5e-324, v


@needs_kernel
def test_exp_specials_and_tail():
    """inf, -inf and NaN; lengths that are not a multiple of 8 touch nothing beyond the view."""
    specials = torch.tensor([math.inf, -math.inf, math.nan, 0.0], dtype=torch.float64)
    out = native.exp_(specials.clone())
    assert out[0] == math.inf and out[1] == 0.0 and math.isnan(out[2]) and out[3] == 1.0
    buf = torch.zeros(16, dtype=torch.float64)
    native.exp_(buf[:13])
    assert torch.equal(buf[:13], torch.ones(13, dtype=torch.float64))
    assert torch.equal(buf[13:], torch.zeros(3, dtype=torch.float64))


@needs_kernel
@pytest.mark.parametrize(("num", "dz"), [(2, 8), (587, 7)])
def test_categorical_normal_are_torchs_draws(num, dz):
    """``categorical_normal`` against torch's two calls from the same generator: the grid values
    exactly (a distribution with zero entries, not normalised), the generator left in the same
    state, and each normal against the exact Box-Muller value of the uniform torch draws for it
    (mpmath at 120 bits): within 5 ulp (its log, sine and cosine within 1 ulp each, the square
    root and the product within half an ulp: 2.5 units of 2^-53 relative, up to 5 ulp where the
    result lies low in its binade), where n = num dz is not a multiple of 16 the last sixteen
    drawn again; torch's own normals within 2 ulp of the same values (so that a wrong form or
    order would show)."""
    prob = torch.tensor([0.3, 0.0, 1.2, 0.05, 0.0, 0.7], dtype=torch.float64)
    gen, twin = torch.Generator().manual_seed(num), torch.Generator().manual_seed(num)
    g, ours = native.categorical_normal(prob, num, dz, gen)
    assert torch.equal(g, torch.multinomial(prob, num, replacement=True, generator=twin))
    theirs = torch.randn(num, dz, generator=twin, dtype=torch.float64).reshape(-1)
    assert torch.equal(gen.get_state(), twin.get_state())
    ours, n = ours.reshape(-1), num * dz
    replay = torch.Generator().manual_seed(num)
    torch.rand(num, generator=replay, dtype=torch.float64)  # the grid values' uniforms
    uniforms = torch.rand(n + (16 if n % 16 else 0), generator=replay, dtype=torch.float64)
    uniforms = uniforms.tolist()
    mpmath.mp.prec = 120
    tail = n - 16 if n % 16 else n  # the repeated last block writes the last sixteen draws
    for start in list(range(0, n - 15, 16)) + ([n] if n % 16 else []):
        base = min(start, n - 16)
        for j in range(8):
            rho = mpmath.sqrt(-2 * mpmath.log(1 - mpmath.mpf(uniforms[start + j])))
            theta = mpmath.mpf(2.0 * math.pi * uniforms[start + j + 8])
            for k, exact in (
                (base + j, rho * mpmath.cos(theta)),
                (base + j + 8, rho * mpmath.sin(theta)),
            ):
                if start < n and k >= tail:
                    continue  # drawn again by the last block
                unit = math.ulp(float(exact))
                assert abs(mpmath.mpf(float(ours[k])) - exact) <= 5 * unit, k
                assert abs(mpmath.mpf(float(theirs[k])) - exact) <= 2 * unit, k


@needs_kernel
def test_categorical_normal_few_draws_and_bad_distributions():
    """One draw or fewer than 16 normals (which torch draws another way) are torch's own draws;
    a negative, NaN or all-zero distribution is refused (its uniforms drawn, nothing
    returned)."""
    gen, twin = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    prob = torch.tensor([0.5, 0.2, 0.3], dtype=torch.float64)
    for num, dz in ((3, 5), (1, 20)):
        g, eps = native.categorical_normal(prob, num, dz, gen)
        assert torch.equal(g, torch.multinomial(prob, num, replacement=True, generator=twin))
        assert torch.equal(eps, torch.randn(num, dz, generator=twin, dtype=torch.float64))
    for bad in ([0.5, -0.1], [0.5, math.nan], [0.0, 0.0]):
        with pytest.raises(ValueError, match="prob must be"):
            native.categorical_normal(torch.tensor(bad, dtype=torch.float64), 10, 4, gen)


def _problem(streams: int, U: int, L: int, D: int, K: int, gen: torch.Generator, phase=False):
    """Random inputs of :func:`native.psi2_groups` and the dense quantities they stand for: the
    exponent ``d_i^T H d_j + d_i^T M_a d_i + d_j^T M_b d_j + c + lp_i + lp_j`` formed whole, its
    sum of absolute terms, and psi1's exponent ``d_i^T P d_i + c_1 + lp_i`` with its sum of
    absolute terms."""
    n, up, kp = U * L, -(-U // 8) * 8, -(-K // 8) * 8
    f64 = {"generator": gen, "dtype": torch.float64}
    points = torch.randn(n, D, **f64)
    mu = 0.5 * torch.randn(streams, D, **f64)
    forms = 0.3 * torch.randn(streams, 4, D, D, **f64) / D
    const = torch.randn(streams, 2, **f64)
    log_phase = -torch.rand(streams, n, **f64) if phase else None
    A = torch.randn(n, n, **f64)
    kinv = A + A.T
    beta = torch.randn(n, D, **f64)
    phi = torch.rand(K, U, **f64)
    cols = torch.zeros(L, up, dtype=torch.long)
    cols[:, :U] = torch.arange(U)[None, :] * L + torch.arange(L)[:, None]
    real = torch.zeros(L, up, dtype=torch.bool)
    real[:, :U] = True
    cols, real = cols.reshape(-1), real.reshape(-1)
    args = (
        points, cols, mu, forms, const, log_phase, beta,
        (beta[cols] * real[:, None]).T.contiguous(),
        (kinv[:, cols] * real).contiguous(),
        torch.nn.functional.pad(phi.T, (0, kp - K, 0, up - U)).contiguous(),
        U,
    )  # fmt: skip
    d = points - mu[:, None, :]  # [S, N, D]
    H, Ma, Mb, P = forms.unbind(1)
    terms = [
        torch.einsum("sia,sab,sjb->sijab", d, H, d).flatten(-2),
        torch.einsum("sia,sab,sib->siab", d, Ma, d).flatten(-2)[:, :, None].expand(-1, -1, n, -1),
        torch.einsum("sja,sab,sjb->sjab", d, Mb, d).flatten(-2)[:, None].expand(-1, n, -1, -1),
        const[:, None, None, :1].expand(-1, n, n, 1),
    ]
    ones = [
        torch.einsum("sia,sab,sib->siab", d, P, d).flatten(-2),
        const[:, None, 1:].expand(-1, n, 1),
    ]
    if log_phase is not None:
        terms += [log_phase[:, :, None, None].expand(-1, -1, n, 1)]
        terms += [log_phase[:, None, :, None].expand(-1, n, -1, 1)]
        ones += [log_phase[..., None]]
    terms, ones = torch.cat(terms, -1), torch.cat(ones, -1)  # [S, N, N, terms], [S, N, terms]
    return args, (
        terms.sum(-1),
        terms.abs().sum(-1),
        ones.sum(-1),
        ones.abs().sum(-1),
        kinv,
        beta,
        phi,
    )


@needs_kernel
@pytest.mark.parametrize(
    ("U", "L", "D", "K", "phase"),
    [(11, 3, 4, 5, False), (8, 4, 1, 13, True), (5, 2, 8, 9, False), (9, 5, 3, 25, True)],
)
def test_group_sums_equal_the_dense_formulas(U, L, D, K, phase):
    """``T`` and the pairs of weighted second moments against ``E = exp(exponent)`` formed whole
    from its terms. Each sum differs from the exact one by at most (first order) ``eps`` times
    its sum of absolute terms times: 2 ulp of the exponential and, per side, the exponent's
    sum of absolute terms times its longest summation chain (``D`` products in ``d^T H``, then
    ``D + 2`` columns, plus the two roundings of each offset ``d``: ``2 D + 4``); and the length
    of the summation chains after it (the kernel adds L rows, then L column blocks, then U and
    U groups; torch's sums are no longer)."""
    gen = torch.Generator().manual_seed(U * 100 + D)
    args, (exponent, spread, exponent1, spread1, kinv, beta, phi) = _problem(
        3, U, L, D, K, gen, phase
    )
    T, out, p1 = (t.clone() for t in native.psi2_groups(*args))
    # psi1: 2 ulp of the exponential, the form's chain (D products, then D terms) and d's rounding
    bound = (2 + (2 * D + 4) * spread1) * EPS * torch.exp(exponent1)
    assert bool(((p1 - torch.exp(exponent1)).abs() <= bound).all())
    E = torch.exp(exponent)
    n = U * L
    per_term = 2 * (2 + (2 * D + 4) * float(spread.max()))
    block = (E * kinv).view(3, U, L, U, L).sum((2, 4))
    block_abs = (E * kinv).abs().view(3, U, L, U, L).sum((2, 4))
    assert bool(((T[..., :U] - block).abs() <= (per_term + 4 * L) * EPS * block_abs).all())
    assert bool((T[..., U:] == 0).all())
    group = torch.arange(n) // L
    Wk = phi[:, group, None] * beta  # [K, N, D]: phi[k, u_i] beta_ia
    want = torch.einsum("kia,sij,kjb->skab", Wk, E, Wk)
    want_abs = torch.einsum("kia,sij,kjb->skab", Wk.abs(), E, Wk.abs())
    a, b = torch.triu_indices(D, D)
    got = out[:, :-1, :K].transpose(1, 2)  # [S, K, pairs]
    bound = (per_term + 4 * (L + U) + 8) * EPS * want_abs[..., a, b]
    assert bool(((got - want[..., a, b]).abs() <= bound).all())
    assert bool((out[..., K:] == 0).all())
    # the trace row: sum_ij phi[k, u_i] psi2_ij K^-1_ij phi[k, u_j], chains as for the pairs
    trace = torch.einsum("ki,sij,kj->sk", phi[:, group], E * kinv, phi[:, group])
    trace_abs = torch.einsum("ki,sij,kj->sk", phi[:, group], (E * kinv).abs(), phi[:, group])
    bound = (per_term + 4 * (L + U) + 8) * EPS * trace_abs
    assert bool(((out[:, -1, :K] - trace).abs() <= bound).all())


@needs_kernel
@pytest.mark.parametrize("D", [1, 3, 4, 8])
def test_rbf_forms_equal_the_torch_forms(D, generator):
    """The kernel's quadratic forms of psi2 and psi1 against
    :func:`~hgpdm_torch.expectations.rbf_psi2_quadratic` and ``rbf_psi1_quadratic`` (a zero
    weight included, coef != 1), within the rounding of a D x D Cholesky factor and inverse of
    ``B = I + S Sigma S`` (``B >= I``: relative error a few ``D eps cond(B)`` of the forms'
    scale); a NaN covariance sets its stream's status only."""
    from hgpdm_torch.expectations import Term, rbf_psi1_quadratic, rbf_psi2_quadratic

    S = 5
    A = torch.randn(S, D, D, generator=generator, dtype=torch.float64)
    Sigma = A @ A.mT / D + 0.05 * torch.eye(D, dtype=torch.float64)
    w = torch.rand(D, generator=generator, dtype=torch.float64) * 3
    w[0] = 0.0  # an unused column
    coef = 1.7
    term = Term("rbf", torch.tensor(coef, dtype=torch.float64), w, None)
    forms, consts, status = native.rbf_forms(Sigma, w, coef)
    assert not status.any()
    H, M_a, M_b, const = rbf_psi2_quadratic(term, term, Sigma)
    P, const1 = rbf_psi1_quadratic(term, Sigma)
    cond = float(torch.linalg.cond(torch.eye(D) + 6 * Sigma).max())
    rel = 16 * D * EPS * cond
    for got, want in zip(forms.unbind(1), (H, M_a, M_b, P), strict=True):
        torch.testing.assert_close(got, want, rtol=rel, atol=rel * float(want.abs().max()))
    want = torch.stack([const, const1 + math.log(coef)], -1)
    torch.testing.assert_close(consts, want, rtol=rel, atol=rel)
    Sigma[2] = math.nan
    Sigma[3] = torch.eye(D, dtype=torch.float64)
    Sigma[3, 0, -1] = math.inf  # above the diagonal, which a Cholesky factor never reads
    assert native.rbf_forms(Sigma, w, coef)[2].tolist() == [0, 0, 1, 1, 0]


@needs_kernel
def test_threads_use_their_own_buffers():
    """The outputs live in per-thread scratch buffers: four threads at once (ctypes releases the
    GIL) give each what it gives alone, bit for bit (the same code on the same inputs)."""
    problems = [_problem(2, 9, 3, 3, 6, torch.Generator().manual_seed(i))[0] for i in range(4)]
    alone = [tuple(t.clone() for t in native.psi2_groups(*p)) for p in problems]
    results: dict[int, list] = {i: [] for i in range(4)}

    def work(i: int) -> None:
        for _ in range(20):
            results[i].append(tuple(t.clone() for t in native.psi2_groups(*problems[i])))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in range(4):
        for got in results[i]:
            assert all(torch.equal(g, w) for g, w in zip(got, alone[i], strict=True))


@needs_kernel
def test_usable_only_where_no_gradient_is_recorded():
    """A tensor that requires a gradient goes to the kernel only where autograd is off (the
    kernel records none); float32 never does."""
    leaf = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    assert not native.usable(leaf)
    with torch.no_grad():
        assert native.usable(leaf)
        assert not native.usable(leaf.detach().float())


@needs_kernel
def test_inputs_are_checked():
    args, _ = _problem(1, 9, 2, 2, 4, torch.Generator().manual_seed(1))
    with pytest.raises(TypeError, match="points must be a contiguous float64 CPU tensor"):
        native.psi2_groups(args[0].float(), *args[1:])
    with pytest.raises(TypeError, match="forms must be a contiguous"):
        native.psi2_groups(*args[:3], args[3].transpose(2, 3), *args[4:])
    with pytest.raises(TypeError, match="cols must be a contiguous 1-D int64"):
        native.psi2_groups(args[0], args[1].int(), *args[2:])
    beyond = args[1].clone()
    beyond[-1] = 18  # one past the last point
    with pytest.raises(ValueError, match=r"cols must index the 18 points, got values in \[0, 18\]"):
        native.psi2_groups(args[0], beyond, *args[2:])
    with pytest.raises(ValueError, match=r"log_phase must have shape \(1, 18\)"):
        native.psi2_groups(*args[:5], torch.zeros(1, 17, dtype=torch.float64), *args[6:])
    with pytest.raises(ValueError, match="Up and Kp multiples of 8"):
        native.psi2_groups(*args[:-1], 6)
    wide = torch.zeros(18, 9, dtype=torch.float64)
    with pytest.raises(ValueError, match="1 <= D <= 8"):
        native.psi2_groups(wide, *args[1:])
    with pytest.raises(TypeError, match="t must be a contiguous float64"):
        native.exp_(torch.zeros(3, dtype=torch.float32))


@pytest.fixture
def fresh_library(monkeypatch, tmp_path):
    """An empty cache folder and no library loaded yet (restored afterwards)."""
    monkeypatch.setenv("HGPDM_TORCH_CACHE", str(tmp_path))
    monkeypatch.setattr(native, "supported", lambda: True)
    native._library.cache_clear()
    yield tmp_path
    native._library.cache_clear()


def _fake_compiler(folder, version_ok: bool):
    script = folder / "fakecc"
    script.write_text(
        "#!/bin/sh\n"
        f'if [ "$1" = --version ]; then echo fake 1.0; exit {0 if version_ok else 3}; fi\n'
        'echo "fakecc: error: no such instruction" >&2; exit 1\n'
    )
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    return str(script)


@pytest.mark.parametrize("how", ["none", "broken", "fails", "read-only"])
def test_no_compiler_warns_once_and_torch_runs(how, fresh_library, monkeypatch, generator):
    """No compiler, one that does not run, one whose build fails: one warning naming why, then
    the torch path, with the materialised path's moments."""
    if how == "none":
        monkeypatch.setattr(native, "_compiler", lambda: None)
        why = "no C compiler found"
    elif how == "read-only":  # a cache folder that cannot be made (a file stands in its way)
        (fresh_library / "file").write_text("")
        monkeypatch.setenv("HGPDM_TORCH_CACHE", str(fresh_library / "file" / "cache"))
        cc = _fake_compiler(fresh_library, version_ok=True)
        monkeypatch.setattr(native, "_compiler", lambda: cc)
        why = "cannot write the cache folder"
    else:
        cc = _fake_compiler(fresh_library, version_ok=how == "fails")
        monkeypatch.setattr(native, "_compiler", lambda: cc)
        why = "does not run" if how == "broken" else "failed: fakecc: error"
    with pytest.warns(RuntimeWarning, match=why):
        assert not native.available()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not native.available()  # once per process
        post, values = _iddm_posterior("iddm_continuous", generator)
        fast = SharedTransition(post, values)
        mu, S = _gaussians(4, DX, generator)
        got = fast.moments(mu, S)
    with settings.moment_path("materialised"):
        want = fast.moments(mu, S)
    _close(got, want, 64 * EPS * len(post.train_inputs))
    assert not list(fresh_library.glob("*.so"))  # nothing half-built left behind


@pytest.mark.skipif(
    not (native.supported() and (shutil.which("cc") or shutil.which("gcc"))),
    reason="needs an AVX-512F and DQ CPU and a C compiler",
)
def test_builds_into_an_empty_cache(fresh_library):
    """The first use builds the library into the cache folder under its hash name, and a later
    process (the cache cleared) loads it without building again."""
    assert native.available()
    built = list(fresh_library.glob("native_psi2_*.so"))
    assert len(built) == 1 and not list(fresh_library.glob("tmp*"))
    stamp = built[0].stat().st_mtime_ns
    native._library.cache_clear()
    assert native.available() and built[0].stat().st_mtime_ns == stamp
    with settings.native_kernels(False):
        assert not native.available()


@needs_kernel
def test_filter_takes_larger_chunks_on_the_kernel(continuous_iddm):
    """Where the compiled kernel runs the transition, the filter's default chunk of streams is
    :data:`~hgpdm_torch.tiling.NATIVE_STREAM_CHUNK` (no psi2 tile per stream to keep in cache);
    with it off, or in float32, the torch tiles' :data:`~hgpdm_torch.tiling.CPU_STREAM_CHUNK`."""
    from hgpdm_torch.inference.intention import OnlineIntentionFilter
    from hgpdm_torch.tiling import CPU_STREAM_CHUNK, NATIVE_STREAM_CHUNK

    grid = torch.linspace(-1.2, 1.2, 9)
    f = OnlineIntentionFilter(continuous_iddm, grid, batch_size=3)
    assert f.transition.compiled() and f.chunk_size == NATIVE_STREAM_CHUNK
    with settings.native_kernels(False):
        f = OnlineIntentionFilter(continuous_iddm, grid, batch_size=3)
        assert not f.transition.compiled() and f.chunk_size == CPU_STREAM_CHUNK
