"""Table-tennis target prediction experiment (Sec. 3.5), smoke sizes."""

from __future__ import annotations

import pytest
import torch

from hgpdm_torch.experiments.target_prediction import (
    HORIZONS_MS,
    target_prediction,
)
from hgpdm_torch.models import LinearIDDM
from hgpdm_torch.robots.table_tennis.opponent import sample_strokes

#: the experiment at smoke sizes fits its models a few steps on purpose (each FitResult says it
#: stopped at the step limit): their ConvergenceWarnings are expected here, and only here
SHORT_FITS = pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")


@SHORT_FITS
@pytest.mark.filterwarnings("ignore:LinearIDDM. a phase has:UserWarning")  # smoke sizes
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
    assert any(m.startswith("ridge") for m in methods)
    assert any(m.startswith("ProMP (") for m in methods)
    assert set(table.meta["promp_options"]) == {"num_basis", "speeds", "reg"}
    assert len(table.meta["train_mae_online"]) == len(HORIZONS_MS)
    for name in (
        "online", "online calibrated", "online sparse M=30", "batch", "gpr", "ridge", "promp",
        "median",
        "linear iddm", "linear iddm calibrated", "linear iddm interaction calibrated",
        "linear iddm selected", "linear iddm interaction selected", "linear iddm mixture",
        "phase iddm", "phase iddm + linear mixture",
    ):  # fmt: skip
        assert len(table.meta["mae"][name]) == len(HORIZONS_MS)
    # the credible sets are scored at T = 1 and at the temperature fitted on the CV folds
    t = table.meta["temperature"]
    assert t > 0 and any(m.endswith(f"T={t:.3g} (CV)") for m in methods)
    covered = [r["90% set coverage [%]"] for r in table.rows if "90% set coverage [%]" in r]
    assert len(covered) == 10 and all(0 <= c <= 100 for c in covered)
    # the phase-aware IDDM: the options chosen by target_sweep's CV, the selected kernel and Dx
    assert table.meta["phase_iddm"]["options"]["phase_width"] == "0.25"
    assert any("per phase, transition scales (phase width" in m for m in methods)
    assert table.meta["phase_iddm"]["options"]["scale_transitions"] == "True"
    # the linear IDDM's prior is the evidence maximum of the training strokes
    linear = table.meta["linear_iddm"]
    strokes14 = sample_strokes(22, generator=torch.Generator().manual_seed(0))
    refit = LinearIDDM().fit(strokes14.obs[:14], strokes14.targets[:14])
    assert (linear["coef_precision"], linear["noise_prior"]) == refit.prior
    assert linear["noise"] == refit.noise_kind
    assert any(m.startswith("linear IDDM per phase") for m in methods)
    # and its calibrated row: the same prior, the temperature and forgetting of its own CV
    calibrated = table.meta["linear_iddm_calibrated"]
    cv = LinearIDDM(temperature="cv", forgetting="cv")
    cv.fit(strokes14.obs[:14], strokes14.targets[:14])
    assert (linear["temperature"], linear["forgetting"]) == (1.0, 0.0)
    assert (calibrated["temperature"], calibrated["forgetting"]) == (cv.temperature, cv.forgetting)
    assert any(m.endswith(f"eps={cv.forgetting:.3g} (T, eps by CV))") for m in methods)
    assert table.meta["linear_iddm_interaction_calibrated"]["interaction_rank"] == 1
    assert any("interaction rank 1 (T, eps by CV)" in m for m in methods)
    # the selected row: noise kind and prior by the same cross-validation, not the evidence
    selected = table.meta["linear_iddm_selected"]
    sel = LinearIDDM(select="cv", temperature="cv", forgetting="cv")
    sel.fit(strokes14.obs[:14], strokes14.targets[:14])
    assert (selected["noise"], selected["coef_precision"], selected["noise_prior"]) == (
        sel.noise_kind, *sel.prior
    )  # fmt: skip
    assert any("interaction rank 1 (all by CV)" in m for m in methods)
    assert any(m.startswith("BeliefMixture") for m in methods)
    assert set(table.meta["calibration"]) == {"T=1", "fitted T"}
    # the median row equals an independent recomputation on the same strokes
    strokes = sample_strokes(22, generator=torch.Generator().manual_seed(0))
    y = strokes.targets
    mae = 100 * float((y[14:] - y[:14].median()).abs().mean())
    for value, _ in table.meta["mae"]["median"]:
        assert abs(value - mae) < 1e-9


def test_bad_options():
    with pytest.raises(ValueError, match="init"):
        target_prediction(n_train=4, n_test=2, init="ica")
    with pytest.raises(ValueError, match="cv_folds"):
        target_prediction(n_train=4, n_test=2, cv_folds=3)
