"""Every benchmark runs in its --quick smoke mode and writes its JSON table."""

from __future__ import annotations

import importlib
import json
import pkgutil
from pathlib import Path

import pytest
import torch

import benchmarks
from benchmarks.__main__ import NOT_BENCHMARKS

NAMES = sorted(
    m.name
    for m in pkgutil.iter_modules(benchmarks.__path__)
    if not m.name.startswith("_") and m.name not in NOT_BENCHMARKS
)


def test_benchmarks_are_found():
    assert {"hgpdm_fit", "moment_matching", "online_intention", "mcp"} <= set(NAMES)


#: quick runs over ~20 s on 2 cores, behind ``slow``: the behaviour they time has fast tests of
#: its own (stroke execution in tests/robots, the regressors in tests/test_baselines.py, the
#: Weird Walking command on a real-data slice in tests/experiments/test_walkers.py)
SLOW = {"table_tennis", "target_information", "weird_walking"}
#: benchmarks of real recordings (``../shared/data``, seen from the project root)
NEEDS_DATA = {
    name: Path("../shared/data/cmu") for name in ("forecast_anatomy", "map_solver", "weird_walking")
}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in NAMES]
)
def test_quick_mode_runs_and_writes_results(name, capsys):
    if name in NEEDS_DATA and not NEEDS_DATA[name].is_dir():
        pytest.skip(f"{NEEDS_DATA[name]} is absent (real recordings, not in the repository)")
    module = importlib.import_module(f"benchmarks.{name}")
    assert module.main(["--quick"]) == 0
    out = Path(benchmarks.__file__).parent / "results" / f"{name}_quick.json"
    table = json.loads(out.read_text())
    assert table["rows"] and table["columns"]
    assert "|" in capsys.readouterr().out  # the printed Markdown table


@pytest.mark.parametrize("name", ["online_intention", "hgpdm_fit", "moment_matching", "mcp"])
def test_device_and_dtype_options(name, capsys):
    """``--device cpu --dtype float32`` runs and writes its own file, not the float64 one."""
    module = importlib.import_module(f"benchmarks.{name}")
    assert module.main(["--quick", "--device", "cpu", "--dtype", "float32"]) == 0
    out = Path(benchmarks.__file__).parent / "results" / f"{name}_cpu_float32_quick.json"
    table = json.loads(out.read_text())
    assert table["rows"] and table["meta"]["dtype"] == "float32"
    assert "|" in capsys.readouterr().out


def test_device_options_only_go_to_benchmarks_that_take_them(capsys):
    """``--device`` with a CPU-only benchmark is refused instead of silently running it on the
    CPU and overwriting its result file."""
    from benchmarks.__main__ import DEVICE_AWARE, main

    assert "target_sweep" not in DEVICE_AWARE and "online_intention" in DEVICE_AWARE
    assert main(["target_sweep", "--device", "cpu"]) == 2
    assert "take no --device" in capsys.readouterr().err


def test_replicate_ratio_interval_against_a_plain_loop():
    """The two-stage bootstrap of target_replicates: replicates drawn with replacement, then
    strokes within each drawn replicate, paired between the methods, ratio of sums."""
    from benchmarks.target_replicates import _ratio_interval

    gen = torch.Generator().manual_seed(0)
    err = [torch.rand(12, 4, generator=gen, dtype=torch.float64) for _ in range(3)]
    ref = [e + 0.3 * torch.rand(12, 4, generator=gen, dtype=torch.float64) for e in err]
    assert _ratio_interval(ref, ref, 200, 0) == (1.0, 1.0)
    lo, hi = _ratio_interval(err, ref, 400, 1)
    # the same draws, in the same order from the same generator, by a loop
    draw = torch.Generator().manual_seed(1)
    which = torch.randint(3, (400, 3), generator=draw)
    strokes = torch.randint(12, (400, 3, 12), generator=draw)
    ratios = []
    for b in range(400):
        num = sum(float(err[r][strokes[b, i], -1].sum()) for i, r in enumerate(which[b].tolist()))
        den = sum(float(ref[r][strokes[b, i], -1].sum()) for i, r in enumerate(which[b].tolist()))
        ratios.append(num / den)
    expected = torch.quantile(torch.tensor(ratios, dtype=torch.float64),
                              torch.tensor([0.025, 0.975], dtype=torch.float64))  # fmt: skip
    assert (lo, hi) == pytest.approx(expected.tolist(), rel=1e-12)
    point = float(sum(e[:, -1].sum() for e in err) / sum(r[:, -1].sum() for r in ref))
    assert lo < point < hi


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--draws=0"], "at least two seeds"),
        (["--draws=0,x"], "comma-separated seeds"),
        (["--workers=0"], "positive integer"),
        (["--workers=two"], "positive integer"),
    ],
)
def test_target_draws_refuses_bad_options(argv, message, capsys):
    """Bad ``--draws``/``--workers`` are refused before any work, with the option named."""
    from benchmarks.target_draws import main

    assert main(argv) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--protocols=foo"], ["--protocols=walkers,"]])
def test_forecast_anatomy_refuses_unknown_protocols(argv, capsys):
    """An unknown protocol is refused before any data is read, naming the valid ones."""
    from benchmarks.forecast_anatomy import main

    assert main(argv) == 2
    assert "weird-walking" in capsys.readouterr().err


def test_pca_reconstruction_against_sklearn():
    """The linear manifold's floor equals sklearn's PCA round trip (fit on the training frames,
    transform and inverse-transform the test frames); and frames inside the training span
    reconstruct exactly."""
    from sklearn.decomposition import PCA

    from benchmarks.forecast_anatomy import pca_reconstruction_rmse

    gen = torch.Generator().manual_seed(0)
    train = torch.randn(60, 7, generator=gen, dtype=torch.float64) * torch.arange(1.0, 8.0)
    test = torch.randn(15, 7, generator=gen, dtype=torch.float64) * torch.arange(1.0, 8.0)
    pca = PCA(3).fit(train.numpy())
    back = torch.from_numpy(pca.inverse_transform(pca.transform(test.numpy())))
    expected = float((back - test).pow(2).mean().sqrt())
    # a projection of O(1) numbers through an SVD: agreement to ~1e-12 relative on any machine
    assert pca_reconstruction_rmse(train, test, 3) == pytest.approx(expected, rel=1e-9)
    centre = train.mean(0)
    basis = torch.from_numpy(pca.components_)  # [3, 7], orthonormal rows
    inside = centre + (test - centre) @ basis.T @ basis
    assert pca_reconstruction_rmse(train, inside, 3) < 1e-12
    assert pca_reconstruction_rmse(train, test, 7) < 1e-12
