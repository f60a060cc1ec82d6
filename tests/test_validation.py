"""``validation.check_finite``: its one-sum fast path against an entry-by-entry oracle."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from hgpdm_torch.validation import check_finite


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_check_finite_refuses_exactly_the_tensors_with_a_bad_entry(dtype):
    """Random tensors with NaN, +inf or -inf put at random places raise, naming the argument;
    finite ones pass, including those whose sum overflows (which the entries then settle) and
    one that records a gradient (no warning)."""
    gen = torch.Generator().manual_seed(0)
    big = torch.finfo(dtype).max
    for trial in range(200):
        t = torch.randn(int(torch.randint(1, 50, (1,), generator=gen)), generator=gen, dtype=dtype)
        if trial % 4 == 1:
            t = t * big  # finite entries, a sum that overflows
        if trial % 2 == 0:
            where = int(torch.randint(0, t.numel(), (1,), generator=gen))
            t[where] = (math.nan, math.inf, -math.inf)[trial % 3]
        bad = not all(math.isfinite(v) for v in t.tolist())
        if bad:
            with pytest.raises(ValueError, match="x contains NaN or inf"):
                check_finite(t, "x")
        else:
            check_finite(t, "x")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_finite(torch.ones(3, dtype=dtype, requires_grad=True), "x")
    check_finite(torch.tensor([math.nan, 1.0], dtype=dtype), "x", allow_nan=True)
    with pytest.raises(ValueError, match="x contains inf"):
        check_finite(torch.tensor([math.nan, math.inf], dtype=dtype), "x", allow_nan=True)
