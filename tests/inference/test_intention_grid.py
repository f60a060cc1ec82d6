"""The default intention grid of a continuous g: its size is checked (issue 54)."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.inference import intention_grid
from hgpdm_torch.models import HGPDM


@pytest.fixture(scope="module")
def model() -> HGPDM:
    gen = torch.Generator().manual_seed(0)
    seqs = [torch.randn(6, 3, generator=gen) for _ in range(3)]
    return HGPDM(seqs, [-1.0, 0.0, 2.0], 2, intention="continuous")


def test_grid_spans_the_training_range(model):
    grid = intention_grid(model, num=2)
    torch.testing.assert_close(grid[:, 0], torch.tensor([-1.0, 2.0]))


@pytest.mark.parametrize("num", [0, 1, -3])
def test_grid_of_fewer_than_two_values_is_refused(model, num):
    # num = 0 returned an empty grid, so inference had nothing to score
    with pytest.raises(ValueError, match=f"num must be at least 2.*got {num}"):
        intention_grid(model, num=num)


@pytest.mark.parametrize("num", [2.5, True, "25"])
def test_grid_size_must_be_an_int(model, num):
    with pytest.raises(TypeError, match="num must be an int"):
        intention_grid(model, num=num)
