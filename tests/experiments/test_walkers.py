"""The CMU forecasting experiment (Walkers / Weird Walking): folds, a small real run in both
evaluations, and the command line (which says what trials it found, or stops naming the missing
ones, before any work)."""

from __future__ import annotations

import math
import shutil
from functools import partial
from pathlib import Path

import pytest

from hgpdm_torch.datasets.cmu import Protocol, load_protocol
from hgpdm_torch.datasets.walkers import Standardizer
from hgpdm_torch.experiments.style_recognition import forecast_windows
from hgpdm_torch.experiments.walkers import (
    DEFAULT_FEATURES,
    DEFAULT_FIT_STEPS,
    DEFAULT_LATENT_DIM,
    DEFAULT_MEASUREMENT_POINTS,
    FALLBACK_FEATURES,
    FALLBACK_FIT_STEPS,
    FALLBACK_LATENT_DIM,
    FALLBACK_MEASUREMENT_POINTS,
    METHODS,
    _protocol_choice,
    compare_runs,
    loto_folds,
    main,
    walkers,
)
from hgpdm_torch.results import ResultTable

#: the experiment at smoke sizes fits its models a few steps on purpose (each FitResult says it
#: stopped at the step limit): their ConvergenceWarnings are expected here, and only here
SHORT_FITS = pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")
CMU = Path("../shared/data/cmu")
REAL = pytest.mark.skipif(not CMU.is_dir(), reason="../shared/data/cmu absent: real-data test")


def test_leave_one_trial_out_folds_skip_a_labels_only_trial():
    folds, untestable = loto_folds([0, 0, 1, 2, 2, 2])
    assert untestable == [2]
    assert [held for _, held in folds] == [[0], [1], [3], [4], [5]]
    for train, held in folds:  # every other trial trains, the untestable one included
        assert held[0] not in train and sorted(train + held) == list(range(6))


@REAL
@SHORT_FITS
def test_small_cv_run_has_every_method_and_an_exact_baseline():
    table = walkers("walkers", lengths=(4,), fit_steps=3, stride=8, max_folds=1)
    rows = {r["trial"]: r for r in table.rows}
    assert set(rows) == {"07_01", "average", "SEM"}
    assert table.meta["not testable by leave-one-trial-out"] == ["08_02"]
    assert table.meta["missing training trials"] == ["07_03", "08_01", "08_03"]
    for m in METHODS:
        assert math.isfinite(rows["07_01"][m]) and rows["07_01"][m] > 0
    assert 0 <= rows["07_01"]["accuracy"] <= 1
    # repeat-last-frame RMSE recomputed independently: 07_01 held out, the 7 others train
    data = load_protocol("walkers", folder=CMU)
    train = [s for s, t in zip(data.sequences, data.trials, strict=True) if t != "07_01"]
    std = Standardizer().fit(train)
    z, nxt, _ = forecast_windows([std.transform(data.sequences[0])], [0], 4, 8)
    want = float((z[:, -1] - nxt).pow(2).mean().sqrt())
    assert rows["07_01"]["repeat last frame"] == pytest.approx(want, rel=1e-12)
    fits = table.meta["fits"][0]
    assert fits["held out"] == "07_01" and fits["H-GPDM"]["steps"] == 3
    # the protocol's own CV choice (DEFAULT_OPTIONS["walkers"]) is what ran
    assert table.meta["model_options"]["learn_measurement_width"] == "False"
    # and its pseudo-input count (500) exceeds the fold's frames: the exact GP ran
    assert table.meta["measurement_points"] is None
    assert table.meta["features"] == DEFAULT_FEATURES["walkers"] == "velocity"


@REAL
@SHORT_FITS
def test_test_trials_are_scored_and_absent_ones_listed(tmp_path):
    """A protocol of one's own: two subjects, test trials in a separate folder without the
    skeletons (they come from the training folder), one test trial absent."""
    for name in ("07_02.amc", "35_03.amc"):
        shutil.copy(CMU / name, tmp_path / name)
    mine = Protocol(
        "mine",
        "subject",
        ("07", "35"),
        (("07_01", "07"), ("35_01", "35"), ("35_02", "35")),
        (("07_02", "07"), ("35_03", "35"), ("35_09", "35")),
        10,
        "none",
    )
    with pytest.raises(ValueError, match="max\\(lengths\\) = 40"):  # 07_02 has 32 rows
        walkers(mine, folder=CMU, test_folder=tmp_path, lengths=(40,), fit_steps=3)
    table = walkers(mine, folder=CMU, test_folder=tmp_path, lengths=(3,), fit_steps=3, stride=6)
    assert table.meta["evaluation"] == "test trials"
    assert table.meta["test trials"] == ["07_02", "35_03"]
    assert table.meta["missing test trials"] == ["35_09"]
    assert [r["trial"] for r in table.rows] == ["07_02", "35_03", "average", "SEM"]
    avg, sem = table.rows[-2:]
    for m in METHODS:
        want = (table.rows[0][m] + table.rows[1][m]) / 2
        assert avg[m] == pytest.approx(want, rel=1e-12)
        assert sem[m] == pytest.approx(abs(table.rows[0][m] - table.rows[1][m]) / 2)
    summary = table.meta["summary"]["3"]
    assert summary["VB H-GPDM / GPDM VB"] == pytest.approx(avg["VB H-GPDM"] / avg["GPDM VB"])
    assert set(summary["per label"]) == {"07", "35"}
    compared = compare_runs([table, table]).rows
    # a protocol of one's own has no CV choice of options: the models' defaults ran
    assert "learn_measurement_width" not in table.meta["model_options"]
    assert len(compared) == 2 and compared[0]["options"] == (
        "Dx 3, 3 MAP steps, sharing 0.0, learned measurement width"
    )
    assert compared[0]["VB H-GPDM / GPDM VB"] == summary["VB H-GPDM / GPDM VB"]
    assert compared[0]["ridge AR (CV) (35)"] == table.rows[1]["ridge AR (CV)"]
    assert compared[0]["GRU (CV)"] == f"{avg['GRU (CV)']:.3f} +- {sem['GRU (CV)']:.3f}"
    # the default pseudo-input count (500) exceeds these 106 training frames: the exact GP,
    # recorded as such; fewer pseudo-inputs than frames are recorded and named
    assert table.meta["measurement_points"] is None
    sparse = walkers(
        mine, folder=CMU, test_folder=tmp_path, lengths=(3,), fit_steps=3, stride=6,
        measurement_points=20,
    )  # fmt: skip
    assert sparse.meta["measurement_points"] == 20
    assert compare_runs([sparse]).rows[0]["options"].endswith("measurement_points 20")
    # a process noise per label: only the H-GPDM's rows change
    noisy = walkers(
        mine, folder=CMU, test_folder=tmp_path, lengths=(3,), fit_steps=3, stride=6,
        noise_per_label=True,
    )  # fmt: skip
    assert noisy.meta["noise_per_label"] is True
    assert len(noisy.meta["fits"][0]["H-GPDM"]["alpha_4 per label"]) == 2
    assert "alpha_4 per label" in compare_runs([noisy]).rows[0]["options"]
    noise_rows = ("repeat last frame", "ridge AR (CV)", "GPDM VB")
    for base, other in zip(table.rows[:2], noisy.rows[:2], strict=True):
        assert all(other[m] == base[m] for m in noise_rows)
    pairs = zip(table.rows[:2], noisy.rows[:2], strict=True)
    assert any(o["VB H-GPDM"] != b["VB H-GPDM"] for b, o in pairs)
    # velocity / lagged features: the GP models see more than the frames, the baselines the
    # same frames
    assert table.meta["features"] == FALLBACK_FEATURES == "frames"
    for kind in ("velocity", "lagged"):
        moving = walkers(
            mine, folder=CMU, test_folder=tmp_path, lengths=(3,), fit_steps=3, stride=6,
            features=kind,
        )  # fmt: skip
        assert moving.meta["features"] == kind
        assert f"{kind} features" in compare_runs([moving]).rows[0]["options"]
        for base, other in zip(table.rows[:2], moving.rows[:2], strict=True):
            assert other["windows"] == base["windows"]
            for m in ("repeat last frame", "ridge AR (CV)"):
                assert other[m] == base[m]
            assert other["VB H-GPDM"] != base["VB H-GPDM"]


def test_cli_rejects_bad_values_before_any_work(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["--stride", "0"])
    assert "positive integer" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "missing")])
    assert "not a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--test-data", str(tmp_path / "missing")])
    assert "--test-data" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--protocol", "four-walkers"])
    assert "invalid choice" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--sharing", "1.0"])
    assert "--sharing" in capsys.readouterr().err
    with pytest.raises(ValueError, match="protocol"):
        walkers("dancers")
    with pytest.raises(ValueError, match="measurement_points"):
        walkers("walkers", measurement_points=0)  # before any file is read
    with pytest.raises(ValueError, match="fit_steps"):
        walkers("walkers", fit_steps=0)
    with pytest.raises(ValueError, match="features"):
        walkers("walkers", features="speed")
    with pytest.raises(ValueError, match="at least 2 frames"):
        walkers("walkers", lengths=(1, 5))  # Walkers' velocity features need a change
    with pytest.raises(SystemExit):
        main(["--features", "speed"])
    assert "invalid choice" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--compare", str(tmp_path / "none.json")])
    assert "--compare" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--noise-per-label", "--sharing", "0.5"])
    assert "--noise-per-label" in capsys.readouterr().err
    with pytest.raises(ValueError, match="noise_per_label"):
        walkers("walkers", noise_per_label=True, sharing=0.5)
    with pytest.raises(TypeError, match="noise_per_label"):
        walkers("walkers", noise_per_label="yes")
    with pytest.raises(ValueError, match="learn_alpha"):
        walkers("walkers", noise_per_label=True, model_options={"learn_alpha": True})


def test_step_count_is_the_protocols_unless_given():
    steps = partial(_protocol_choice, "fit_steps")
    assert steps("weird-walking", "protocol") == 150  # its CV choice (docs page)
    assert steps("walkers", "protocol") == DEFAULT_FIT_STEPS["walkers"] == 300
    assert steps("mine", "protocol") == FALLBACK_FIT_STEPS
    assert steps("weird-walking", 7) == 7
    for bad in (0, -1, 2.0, True, "all", None):
        with pytest.raises(ValueError, match="fit_steps"):
            steps("walkers", bad)


def test_latent_dim_is_the_protocols_unless_given():
    dims = partial(_protocol_choice, "latent_dim")
    assert dims("weird-walking", "protocol") == 10  # its CV choice (docs page)
    assert dims("walkers", "protocol") == DEFAULT_LATENT_DIM["walkers"] == 3  # the thesis's
    assert dims("mine", "protocol") == FALLBACK_LATENT_DIM == 3
    assert dims("walkers", 5) == 5
    for bad in (0, -1, 2.0, True, "all", None):
        with pytest.raises(ValueError, match="latent_dim"):
            dims("walkers", bad)


def test_pseudo_input_count_is_the_protocols_unless_given():
    points = partial(_protocol_choice, "measurement_points")
    assert points("weird-walking", "protocol") == 150
    assert points("walkers", "protocol") == DEFAULT_MEASUREMENT_POINTS["walkers"]
    assert points("mine", "protocol") == FALLBACK_MEASUREMENT_POINTS
    assert points("weird-walking", None) is None  # the exact GP
    assert points("weird-walking", 40) == 40
    for bad in (0, -3, 2.5, True, "all"):
        with pytest.raises(ValueError, match="measurement_points"):
            points("walkers", bad)


def test_features_are_the_protocols_unless_given():
    features = partial(_protocol_choice, "features")
    assert features("walkers", "protocol") == DEFAULT_FEATURES["walkers"] == "velocity"  # CV's
    assert features("weird-walking", "protocol") == DEFAULT_FEATURES["weird-walking"] == "lagged"
    assert features("mine", "protocol") == FALLBACK_FEATURES == "frames"  # the thesis's
    assert features("walkers", "lagged") == "lagged"
    for bad in (0, True, None, "speed"):
        with pytest.raises(ValueError, match="features"):
            features("walkers", bad)


def touch(folder: Path, *names: str) -> Path:
    """Empty CMU files: a run must say what it found, and stop, before reading any."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_text("")
    return folder


def test_cli_stops_before_any_work_naming_the_missing_trials(tmp_path, capsys):
    empty = touch(tmp_path / "empty")
    with pytest.raises(SystemExit):
        main(["--data", str(empty)])
    err = capsys.readouterr().err
    assert f"--data {empty}: no walkers training trial (expected one of 07_01.amc" in err
    one = touch(tmp_path / "one", "35.asf", "35_01.amc", "35_02.amc", "35_03.amc")
    with pytest.raises(SystemExit):  # one subject only: the others' trials named
        main(["--data", str(one)])
    err = capsys.readouterr().err
    assert (
        "no training trial for subject 07 (expected one of 07_01.amc, 07_02.amc, 07_03.amc" in err
    )
    assert "subject 16 (expected one of 16_15.amc, 16_16.amc with 16.asf)" in err
    assert "subject 35" not in err
    singles = touch(tmp_path / "singles", *(f"{s}.asf" for s in ("07", "08", "16", "35")))
    touch(singles, "07_01.amc", "08_02.amc", "16_15.amc", "35_01.amc")
    with pytest.raises(SystemExit):  # every subject once: CV holds nothing out
        main(["--data", str(singles)])
    assert "CV needs a subject with two training trials" in capsys.readouterr().err
    # --test-data holding no test trial: never filled from --data, which holds one
    touch(singles, "35_04.amc")
    with pytest.raises(SystemExit):
        main(["--data", str(singles), "--test-data", str(empty)])
    assert f"--test-data {empty}: no walkers test trial (expected" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError, match="test_folder .*no walkers test trial"):
        walkers("walkers", folder=singles, test_folder=empty, fit_steps=1)
    with pytest.raises(FileNotFoundError, match="folder .*no training trial for subject 07"):
        walkers("walkers", folder=one, fit_steps=1)


def test_cli_says_which_trials_it_found_per_label_before_the_run(tmp_path, capsys, monkeypatch):
    data = touch(tmp_path / "data", "07.asf", "16.asf", "35.asf", "08.asf", "08_02.amc")
    touch(data, "07_01.amc", "07_02.amc", "16_15.amc", "16_16.amc", "35_01.amc", "35_03.amc")
    test = touch(tmp_path / "test", "16_22.amc", "35_04.amc")
    calls = []

    def run(*args, **kwargs):  # the found trials are said before the run starts
        calls.append((kwargs["folder"], kwargs["test_folder"], capsys.readouterr().err))
        return ResultTable("t", ["trial"], meta={})

    monkeypatch.setattr("hgpdm_torch.experiments.walkers.walkers", run)
    assert main(["--data", str(data), "--test-data", str(test)]) == 0
    (folder, test_folder, err) = calls[0]
    assert (folder, test_folder) == (data, test)
    lines = err.splitlines()
    assert lines[0] == (
        f"hgpdm walkers: training trials from --data {data}: subject 07: 07_01, 07_02 (07_03 "
        "missing); subject 08: 08_02 (08_01, 08_03 missing); subject 16: 16_15, 16_16; subject "
        "35: 35_01, 35_03 (35_02 missing)"
    )
    assert lines[1].startswith(f"hgpdm walkers: test trials from --test-data {test}: subject 07: ")
    assert "subject 16: 16_22; subject 35: 35_04 (35_05, 35_06" in lines[1]


def test_compare_names_the_file_that_is_not_a_walkers_table(tmp_path, capsys):
    good = ResultTable("t", ["a"])
    good.to_json(tmp_path / "other.json")
    (tmp_path / "cut.json").write_text('{"title": "walkers", "columns": ["T", "tri')
    (tmp_path / "plain.json").write_text('{"columns": []}')
    expect = {
        "cut.json": "cut.json: not a results table, its JSON is invalid or cut short at line 1",
        "plain.json": "plain.json: not a results table (no 'title', 'rows')",
        "other.json": "other.json: not a table of hgpdm walkers (its meta lacks ['protocol'",
    }
    for name, want in expect.items():
        with pytest.raises(SystemExit):
            main(["--compare", str(tmp_path / name)])
        assert f"error: --compare: {tmp_path / want}" in capsys.readouterr().err
    with pytest.raises(ValueError, match=r"tables\[0\]: not a table of hgpdm walkers"):
        compare_runs([good])
