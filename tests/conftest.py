"""Shared pytest configuration: float64 by default, seeded RNG, CUDA skip marker, the ``device``
fixture."""

from __future__ import annotations

import os

import pytest
import torch

torch.set_default_dtype(torch.float64)
torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))

SMOKE = os.environ.get("HGPDM_SMOKE", "0") == "1"


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
    model.fit(25)
    return model
