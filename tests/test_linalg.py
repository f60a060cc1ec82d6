"""Cholesky with jitter escalation and its error."""

from __future__ import annotations

import math

import pytest
import torch

from hgpdm_torch.linalg import CholeskyError, cholesky_logdet, jitter, psd_cholesky


def test_cholesky_and_logdet_match_dense(generator):
    a = torch.randn(6, 6, generator=generator)
    spd = a @ a.T + 6 * torch.eye(6)
    chol = psd_cholesky(spd)
    torch.testing.assert_close(chol @ chol.T, spd)
    torch.testing.assert_close(cholesky_logdet(chol), torch.logdet(spd))


def test_jitter_rescues_a_singular_psd_matrix(generator):
    v = torch.randn(5, 2, generator=generator)
    singular = v @ v.T  # rank 2
    chol = psd_cholesky(singular)
    assert torch.isfinite(chol).all()
    torch.testing.assert_close(chol @ chol.T, singular, atol=1e-6, rtol=0)


def test_indefinite_matrix_raises_with_advice():
    with pytest.raises(CholeskyError, match="not positive definite"):
        psd_cholesky(torch.diag(torch.tensor([1.0, -1.0])), name="K")
    with pytest.raises(ValueError, match="NaN"):
        psd_cholesky(torch.tensor([[float("nan"), 0.0], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="jitter"), jitter(0.0):
        pass


def test_gaussian_nll_value_and_gradient(generator):
    from scipy.stats import multivariate_normal

    from hgpdm_torch.linalg import gaussian_nll

    a = torch.randn(5, 5, generator=generator)
    y = torch.randn(5, 3, generator=generator)
    cov = a @ a.T + torch.eye(5)
    want = -sum(multivariate_normal.logpdf(y[:, d].numpy(), cov=cov.numpy()) for d in range(3))
    # a 5 x 5 matrix of condition number ~11, by scipy (eigh) and by Cholesky: ~1e-14 relative
    assert float(gaussian_nll(cov, y)) == pytest.approx(want, rel=1e-12)
    a_ = a.clone().requires_grad_(True)
    y_ = y.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda a, y: gaussian_nll(a @ a.T + torch.eye(5), y), (a_, y_), eps=1e-6, atol=1e-6
    )
    with pytest.raises(ValueError, match="cov"):
        gaussian_nll(cov, y[:4])


def test_only_failed_batch_members_get_jitter(generator):
    good = torch.eye(3) * 2.0
    v = torch.randn(3, 1, generator=generator)
    chol = psd_cholesky(torch.stack([good, v @ v.T]))
    torch.testing.assert_close(chol[0], torch.linalg.cholesky(good), rtol=0, atol=0)
    assert torch.isfinite(chol[1]).all()


def test_inf_entry_is_rejected_even_if_factorisable():
    with pytest.raises(ValueError, match="NaN or inf"):
        psd_cholesky(torch.tensor([[4.0, 1.0], [1.0, float("inf")]]))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_positive_definite_matches_the_eigenvalues(dtype):
    """``positive_definite`` against ``eigvalsh``: clearly negative eigenvalues and NaN/inf fail,
    PSD matrices with an exact zero eigenvalue and rounding-level negatives pass."""
    from hgpdm_torch.linalg import positive_definite

    gen = torch.Generator().manual_seed(0)
    q, _ = torch.linalg.qr(torch.randn(50, 4, 4, generator=gen, dtype=torch.float64))
    eig = torch.rand(50, 4, generator=gen, dtype=torch.float64) + 0.1
    eig[:10, 0] = -torch.rand(10, generator=gen, dtype=torch.float64) - 1e-3  # clearly negative
    eig[10:20, 0] = 0.0  # singular PSD
    eig[20:30, 0] = -1e-14  # rounding level
    a = (q * eig[:, None, :]) @ q.transpose(-1, -2)
    a[30, 1, 2] = math.nan
    a[31, 0, 0] = math.inf
    expected = torch.ones(50, dtype=torch.bool)
    expected[:10] = False
    expected[30:32] = False
    assert torch.equal(positive_definite(a.to(dtype)), expected)
