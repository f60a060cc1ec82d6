"""Table-tennis target prediction experiment (Sec. 3.5), smoke sizes."""

from __future__ import annotations

import torch

from hgpdm_torch.experiments.target_prediction import HORIZONS_MS, target_prediction
from hgpdm_torch.robots.table_tennis.opponent import sample_strokes


def test_smoke_run_reports_every_method_and_horizon():
    table = target_prediction(
        n_train=14,
        n_test=8,
        kernels=("linear",),
        latent_dims=(3,),
        grid_size=9,
        fit_steps=5,
        inducing=(30,),
    )
    methods = table.column("method")
    assert methods[0] == "IDDM online" and table.rows[0]["Dx"] == 3
    assert any(m.startswith("IDDM batch") for m in methods)
    assert any(m.startswith("GPR") for m in methods) and methods[-1] == "median"
    assert table.meta["selected"] == {"kernel": "linear", "Dx": 3}
    assert any("sparse M=30" in m for m in methods)
    for name in ("online", "online sparse M=30", "batch", "gpr", "median"):
        assert len(table.meta["mae"][name]) == len(HORIZONS_MS)
    # the median row equals an independent recomputation on the same strokes
    strokes = sample_strokes(22, generator=torch.Generator().manual_seed(0))
    y = strokes.targets
    mae = 100 * float((y[14:] - y[:14].median()).abs().mean())
    for value, _ in table.meta["mae"]["median"]:
        assert abs(value - mae) < 1e-9
