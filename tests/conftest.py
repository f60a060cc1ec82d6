"""Shared pytest configuration: float64 by default, seeded RNG, CUDA skip marker, the ``device``
fixture."""

from __future__ import annotations

import os

import pytest
import torch

torch.set_default_dtype(torch.float64)
torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))

SMOKE = os.environ.get("HGPDM_SMOKE", "0") == "1"

# float64 machine epsilon (2.2e-16). Two computations of the same float64 quantity that take
# different BLAS kernels (another batch shape, thread count, CPU or MKL_CBWR path) agree only to
# a few eps times the quantity's scale and the reduction length, amplified by the condition
# number of any solve on the way: tolerances between them are derived from it, never "to the
# last bit" (docs/design/testing.md#tolerances-that-hold-on-any-ieee-754-machine).
EPS = torch.finfo(torch.float64).eps


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if torch.cuda.is_available():
        return
    skip_gpu = pytest.mark.skip(reason="needs CUDA: torch.cuda.is_available() is False")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip_gpu)


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def device(request: pytest.FixtureRequest) -> torch.device:
    """Each device a test runs on: ``cpu``, and ``cuda`` (marked ``gpu``: skipped, with the
    reason printed by ``-rs``, where CUDA is not available). Tests compare the result on it with
    the CPU float64 one."""
    return torch.device(request.param)


@pytest.fixture
def generator() -> torch.Generator:
    """A seeded CPU generator; tests that draw random numbers take it for reproducibility."""
    return torch.Generator().manual_seed(1234)


@pytest.fixture(scope="session")
def continuous_iddm():
    """A small IDDM with a continuous target, fitted once and shared by inference and decision
    tests (read-only: tests must not modify it)."""
    from hgpdm_torch.datasets import targeted_movements
    from hgpdm_torch.models import IDDM

    torch.manual_seed(0)
    data = targeted_movements(18, 10, 6, noise=0.02, seed=3)
    model = IDDM(
        data.sequences, data.labels, 3, intention="continuous", measurement="linear",
        alpha_g=(4.0, 0.1),
    )  # fmt: skip
    model.fit(25, warn=False)  # a step budget: the tests compare computations, not the fit
    return model


def _gp_rounding(*posteriors) -> float:
    """The sum over ``posteriors`` of ``N * EPS * cond(kinv)``: ``kinv`` is ``(K + noise I)^-1``
    (``N`` training points), or a sparse posterior's ``K_MM^-1 - noise A^-1`` (``N``
    pseudo-inputs)."""
    total = 0.0
    for posterior in posteriors:
        kinv = posterior.kinv
        total += kinv.shape[-1] * EPS * float(torch.linalg.cond(kinv))
    return total


@pytest.fixture(scope="session")
def gp_rounding():
    """``gp_rounding(*posteriors)``: the relative rounding of one prediction or filter step whose
    moments go through the GP ``posteriors`` (e.g. an ``OnlineIntentionFilter``'s ``posterior``,
    its transition GP, and the model's ``measurement_posterior()``).

    Every predicted moment solves with a posterior's N x N ``kinv`` matrix: a solve's backward
    error is up to ``N * EPS`` of the matrix and its forward error that times the matrix's
    condition number, so two computations of a belief that round differently (other BLAS
    kernels: batch shape, threads, CPU) differ by up to ``N * EPS * cond`` times its scale per
    step. For ``continuous_iddm``'s transition GP (noise ``alpha_4 = 1e-4``) it is 3e-8 exact
    (N = 162, condition number 8e5) and 5e-8 for the 40-point DTC (6e6); the measured
    differences used up to 0.15 of it (times the steps taken), on MKL's AVX-512, AVX2 and
    COMPATIBLE paths with 1 or 2 threads.
    """
    return _gp_rounding


def _rbf_rounding(a: torch.Tensor, b: torch.Tensor, lengthscales: torch.Tensor) -> float:
    """How far two implementations of an RBF Gram matrix ``exp(-|a - b|^2 / 2)`` (inputs scaled
    by ``lengthscales``) may differ: gpytorch forms ``|a|^2 + |b|^2 - 2 a.b``, which rounds to
    ``(D + 2) eps (|a| + |b|)^2 <= 2 (D + 2) eps (|a|^2 + |b|^2)`` in each; the kernel moves by
    at most half the difference of the two."""
    a, b = a / lengthscales, b / lengthscales
    norms = float(a.pow(2).sum(-1).max() + b.pow(2).sum(-1).max())
    return 2 * (a.shape[-1] + 2) * EPS * norms


@pytest.fixture(scope="session")
def rbf_rounding():
    """``rbf_rounding(a, b, lengthscales)``: the bound :func:`_rbf_rounding` on the difference of
    two implementations of one RBF Gram matrix."""
    return _rbf_rounding
