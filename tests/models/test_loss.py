"""The MAP objective (Eq. 4-6) against an independent dense SciPy evaluation, and its gradients."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from gpytorch.kernels import AdditiveKernel, ProductKernel
from scipy.stats import multivariate_normal, norm

from hgpdm_torch.models import GPDM, HGPDM, IDDM


def _data(seed: int = 0, lengths=(5, 7, 6, 8), dz: int = 4):
    rng = np.random.default_rng(seed)
    return [torch.as_tensor(rng.normal(size=(n, dz)).cumsum(0) * 0.3) for n in lengths]


def _perturb(model: GPDM, seed: int = 1) -> None:
    """Move every parameter off its initial value so each term of Eq. 6 is exercised."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        model.latent.add_(0.3 * torch.randn(model.latent.shape, generator=gen))
        for name, p in model.named_parameters():
            if p.requires_grad and name != "latent":
                p.add_(0.2 * torch.randn(p.shape, generator=gen))


def _transition_gram(model: GPDM, xin: np.ndarray, gin: np.ndarray | None) -> np.ndarray:
    """The transition kernel of Sec. 2.2.1 / 3.2.2 written out with NumPy; a phase-aware IDDM's
    is that times ``exp(-(p - p')^2 / (2 w^2))`` over the frame indices p (``phase_width`` w)."""
    if getattr(model, "phase_width", None) is not None:
        base, phase = model.transition_kernel.kernels
        p = model.transition_phases().numpy()
        w = float(phase.lengthscale)
        factor = np.exp(-0.5 * (p[:, None] - p[None, :]) ** 2 / w**2)
        return factor * _transition_gram_of(model, base, xin, gin)
    return _transition_gram_of(model, model.transition_kernel, xin, gin)


def _transition_gram_of(model: GPDM, kernel, xin: np.ndarray, gin: np.ndarray | None) -> np.ndarray:
    d2 = ((xin[:, None, :] - xin[None, :, :]) ** 2).sum(-1)
    lin = xin @ xin.T
    kind = model.transition_kind
    if kind in ("discrete", "iddm_discrete"):
        same = (gin[:, None, 0] == gin[None, :, 0]).astype(float)
        if not model.sharing:
            return same * _base_gram(kernel.base_kernel, d2, lin)
        # rho k_0(x, x') + (1 - rho) delta(g, g') k_0(x, x'), each part with its own values
        shared, style = kernel.kernels
        return _base_gram(shared, d2, lin) + same * _base_gram(style.base_kernel, d2, lin)
    a1, a2, a3 = _alphas(model, kernel)
    if kind == "gpdm":
        return a1 * np.exp(-0.5 * a2 * d2) + a3 * lin
    rbf = kernel if kind == "iddm_continuous" else kernel.kernels[0]
    a2g = float(rbf.base_kernel.kernels[1].lengthscale) ** -2  # RBF(x) * RBF(g)
    dg2 = ((gin[:, None, :] - gin[None, :, :]) ** 2).sum(-1)
    k = a1 * np.exp(-0.5 * a2 * d2 - 0.5 * a2g * dg2)
    if kind == "continuous":
        a3g = float(kernel.kernels[2].variance)
        k = k + a3 * lin + a3g * gin @ gin.T
    return k


def _base_gram(base, d2: np.ndarray, lin: np.ndarray) -> np.ndarray:
    """``a1 exp(-a2/2 d2) [+ a3 lin]`` from a ScaleKernel(RBF) [+ linear] base kernel."""
    parts = list(base.kernels) if isinstance(base, AdditiveKernel) else [base]
    a1 = float(parts[0].outputscale)
    a2 = float(parts[0].base_kernel.lengthscale) ** -2
    k = a1 * np.exp(-0.5 * a2 * d2)
    return k + float(parts[1].variance) * lin if len(parts) > 1 else k


def _alphas(model: GPDM, k) -> tuple[float, float, float]:
    """``alpha_1..3`` of the gpdm and continuous kinds (transition kernel ``k``)."""
    scale = k if model.transition_kind.startswith("iddm") else k.kernels[0]
    a1 = float(scale.outputscale)
    inner = scale.base_kernel  # RBF(x), or RBF(x) * RBF(g) for the continuous kinds
    rbf_x = inner.kernels[0] if isinstance(inner, ProductKernel) else inner
    a2 = float(rbf_x.lengthscale) ** -2
    a3 = 0.0 if model.transition_kind.startswith("iddm") else float(k.kernels[1].variance)
    return a1, a2, a3


def dense_negative_log_posterior(model: GPDM) -> float:
    """Eq. 4-6 with SciPy densities, from the model's data and hyperparameter values only."""
    x = model.latent.detach().numpy()
    z = model.observations.numpy()
    m, dz = z.shape
    w = model.scales.detach().numpy()
    noise = float(model.measurement_noise)
    d2 = ((x[:, None] - x[None]) ** 2).sum(-1)
    if model.measurement == "rbf":
        beta1 = float(model.measurement_kernel.lengthscale) ** -2
        kz = np.exp(-0.5 * beta1 * d2)
        log_prior = norm.logpdf(np.log(beta1))
    else:
        kz = x @ x.T
        log_prior = 0.0
    kz = kz + noise * np.eye(m)
    y = (z - z.mean(0)) * w
    log_pz = sum(multivariate_normal.logpdf(y[:, d], np.zeros(m), kz) for d in range(dz))
    log_pz += m * np.log(w).sum()

    lengths = model.lengths.numpy()
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    src = np.concatenate([np.arange(s, s + n - 1) for s, n in zip(starts, lengths, strict=True)])
    seq = np.repeat(np.arange(len(lengths)), lengths - 1)
    gin = model.intentions.numpy()[seq] if hasattr(model, "intentions") else None
    kx = _transition_gram(model, x[src], gin) + float(model.transition_noise) * np.eye(len(src))
    # scale_transitions: column d of Eq. 5 is v_d x_out,d ~ N(0, K_x), Jacobian v_d^m
    v = model.transition_scales.detach().numpy()
    xout = x[src + 1] * v
    log_px = sum(
        multivariate_normal.logpdf(xout[:, d], np.zeros(len(src)), kx) for d in range(x.shape[1])
    )
    log_px += len(src) * np.log(v).sum()
    if model.scale_transitions:
        log_prior += norm.logpdf(np.log(v)).sum()
    log_px += norm.logpdf(x[starts]).sum()
    log_prior += norm.logpdf(np.log(noise)) + norm.logpdf(np.log(w)).sum()
    if model.learn_noise:  # weak log-normal prior of a learned alpha_4, centred on alpha-bar
        a4 = float(model.transition_noise)
        log_prior += norm.logpdf(np.log(a4), np.log(model.alpha_init[3]), model.NOISE_PRIOR_SD)
    return -(log_pz + log_px + log_prior)


CASES = [
    ("gpdm-rbf", lambda s: GPDM(s, 2, measurement="rbf")),
    ("gpdm-linear", lambda s: GPDM(s, 2, measurement="linear")),
    ("hgpdm-discrete-rbf", lambda s: HGPDM(s, [0, 1, 0, 2], 2, num_values=3)),
    ("hgpdm-discrete-linear", lambda s: HGPDM(s, [1, 1, 0, 0], 2, measurement="linear")),
    (
        "hgpdm-continuous",
        lambda s: HGPDM(s, [-0.5, 0.2, 0.9, 0.1], 2, intention="continuous"),
    ),
    (
        "hgpdm-continuous-2d",
        lambda s: HGPDM(s, [[0.1, 1], [0.4, -1], [0.3, 0], [-1, 0.5]], 2, intention="continuous"),
    ),
    ("iddm-discrete", lambda s: IDDM(s, [0, 1, 1, 0], 2, measurement="linear")),
    (
        "iddm-continuous",
        lambda s: IDDM(s, [0.3, -0.8, 0.5, 0.0], 2, intention="continuous", measurement="linear"),
    ),
    ("hgpdm-discrete-shared", lambda s: HGPDM(s, [0, 1, 0, 2], 2, num_values=3, sharing=0.4)),
    ("iddm-discrete-shared", lambda s: IDDM(s, [0, 1, 1, 0], 2, sharing=0.7)),
    ("gpdm-scaled", lambda s: GPDM(s, 2, scale_transitions=True)),
    (
        "iddm-continuous-phase-scaled",
        lambda s: IDDM(
            s,
            [0.3, -0.8, 0.5, 0.0],
            2,
            intention="continuous",
            measurement="linear",
            phase_width=1.5,
            scale_transitions=True,
        ),
    ),  # fmt: skip
    (
        "iddm-discrete-scaled",
        lambda s: IDDM(s, [0, 1, 1, 0], 2, measurement="linear", scale_transitions=True),
    ),
]


@pytest.mark.parametrize("name,build", CASES, ids=[c[0] for c in CASES])
def test_loss_matches_dense_scipy_reference(name, build):
    model = build(_data())
    _perturb(model)
    model.learn_alpha = True  # perturb alpha too: the reference reads the values back
    _perturb(model, seed=2)
    got = float(model.loss().detach())
    want = dense_negative_log_posterior(model)
    assert got == pytest.approx(want, rel=1e-10)


GRAD_CASES = CASES[::2] + CASES[7:]


@pytest.mark.parametrize("name,build", GRAD_CASES, ids=[c[0] for c in GRAD_CASES])
def test_gradcheck_latents_and_hyperparameters(name, build):
    model = build(_data(lengths=(4, 5, 3, 4), dz=3))
    model.learn_alpha = True
    # Larger noise than alpha-bar keeps the objective well conditioned for finite differences.
    model.transition_noise = 0.05
    model.measurement_noise = 0.1
    _perturb(model)
    names = [n for n, p in model.named_parameters() if p.requires_grad]
    values = tuple(
        p.detach().clone().requires_grad_(True)
        for n, p in model.named_parameters()
        if p.requires_grad
    )

    def loss_of(*vals):
        return torch.func.functional_call(model, dict(zip(names, vals, strict=True)), ())

    assert torch.autograd.gradcheck(loss_of, values, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_alpha_is_fixed_by_default_and_learnable():
    model = HGPDM(_data(), [0, 1, 0, 1], 2)
    assert not model.learn_alpha and not model.learn_noise
    fixed = [p for n, p in model.named_parameters() if n.startswith("transition_kernel")]
    assert fixed and not any(p.requires_grad for p in fixed)
    assert not model.raw_transition_noise.requires_grad
    assert HGPDM(_data(), [0, 1, 0, 1], 2, learn_noise=True).raw_transition_noise.requires_grad
    assert float(model.transition_noise) == pytest.approx(1e-4)
    model.learn_alpha = True
    assert all(p.requires_grad for p in fixed)


def test_fixed_noise_has_no_prior_term():
    data = _data()
    learned = HGPDM(data, [0, 1, 0, 1], 2, learn_noise=True)
    fixed = HGPDM(data, [0, 1, 0, 1], 2)
    assert not fixed.raw_transition_noise.requires_grad
    a4 = float(fixed.transition_noise)
    prior = norm.logpdf(np.log(a4), np.log(a4), HGPDM.NOISE_PRIOR_SD)
    got = float(learned.loss() - fixed.loss())
    assert got == pytest.approx(-prior, rel=1e-10)


def test_constant_channels_are_carried_not_modelled():
    data = _data(dz=3)
    padded = [torch.cat([s, torch.full((s.shape[0], 1), 2.5)], dim=1) for s in data]
    base, model = GPDM(data, 2), GPDM(padded, 2)
    assert model.varying.tolist() == [True, True, True, False]
    # The constant channel adds nothing to Eq. 4 (and its scale no prior term).
    assert float(model.loss()) == pytest.approx(float(base.loss()), rel=1e-12)
    mean, var = model.measurement_posterior().predict(torch.randn(5, 2))
    assert torch.allclose(mean[:, 3], torch.full((5,), 2.5), atol=1e-12)
    assert torch.isfinite(var).all()


def test_small_units_are_not_constant():
    data = [s * 1e-13 for s in _data()]
    model = GPDM(data, 2)
    assert bool(model.varying.all())
    with pytest.raises(ValueError, match="every observed dim"):
        GPDM([torch.ones(5, 3), torch.ones(4, 3)], 2)


def test_measurement_width_can_be_kept_fixed(tmp_path):
    from hgpdm_torch.models import load_model

    model = GPDM(_data(), 2, learn_measurement_width=False)
    before = float(model.measurement_kernel.lengthscale)
    assert not model.measurement_kernel.raw_lengthscale.requires_grad
    model.fit(5, warn=False)
    assert float(model.measurement_kernel.lengthscale) == before
    assert float(GPDM(_data(), 2).latent.sub(model.latent).abs().max()) > 0  # latents moved
    model.save(tmp_path / "m.pt")
    assert not load_model(tmp_path / "m.pt").measurement_kernel.raw_lengthscale.requires_grad
