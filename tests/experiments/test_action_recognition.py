"""Action recognition experiment (Table 3.3): BasicMotions and MSRC-12 at smoke sizes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hgpdm_torch.experiments import action_recognition as ar
from hgpdm_torch.experiments.action_recognition import (
    action_recognition,
    load_actions,
    main,
    msrc12_recognition,
)

#: the experiment at smoke sizes fits its models a few steps on purpose (each FitResult says it
#: stopped at the step limit): their ConvergenceWarnings are expected here, and only here
SHORT_FITS = pytest.mark.filterwarnings("ignore::hgpdm_torch.fitting.ConvergenceWarning")

DEV = Path("../shared/data/msrc12_dev.npz")


# ------------------------------------------------------------------------------------------
# BasicMotions (aeon)
# ------------------------------------------------------------------------------------------


def test_loader_subsamples_the_real_data():
    pytest.importorskip("aeon")
    z_train, y_train, z_test, y_test, names = load_actions(subsample=3)
    assert z_train.shape == (40, 34, 6) and z_test.shape == (40, 34, 6)
    assert names == sorted(names) and len(names) == 4
    assert sorted(y_train.unique().tolist()) == [0, 1, 2, 3]


@SHORT_FITS
def test_table_is_consistent_with_its_confusion_matrices():
    pytest.importorskip("aeon")
    table = action_recognition(
        fit_steps=5, windows=(4,), forgettings=(0.2,), max_train=2, max_test=1, subsample=5,
        calibration_folds=2,
    )  # fmt: skip
    methods = table.column("method")
    assert methods[:2] == ["IDDM batch n=4", "IDDM online eps=0.2"]
    assert {"SVM n=5", "GPC n=5", "ProMP (phase estimated)"} <= set(methods)
    decisions = table.meta["n_test"] * table.meta["frames"]
    for row in table.rows:
        m = np.asarray(table.meta["confusion"][row["method"]])
        assert m.shape == (4, 4) and m.sum() == decisions
        assert abs(100 * np.trace(m) / decisions - row["accuracy [%]"]) < 0.06
        assert row["CPU ms/decision"] > 0
        check_coverage(row)
    assert table.meta["fits"][0]["steps"] <= 5
    temps = table.meta["temperatures"]
    assert set(temps) == {"IDDM batch n=4", "IDDM online eps=0.2"}
    assert all(t > 0 for t in temps.values()) and len(table.meta["calibration_fits"]) == 2
    # a temperature with a uniform prior keeps the batch ranking: the same decisions as T = 1
    plain = action_recognition(
        fit_steps=5, windows=(4,), forgettings=(0.2,), max_train=2, max_test=1, subsample=5,
        calibration_folds=None,
    )  # fmt: skip
    assert plain.meta["temperatures"] == {}
    assert plain.meta["confusion"]["IDDM batch n=4"] == table.meta["confusion"]["IDDM batch n=4"]
    with pytest.raises(ValueError, match="calibration_folds"):
        action_recognition(max_train=2, max_test=1, subsample=5, calibration_folds=3)


def check_coverage(row: dict) -> None:
    """The 90% credible sets of the IDDM and the ProMP always hold their decision (the most
    probable class), so they cover the truth at least as often as it is right; the window
    baselines give no probabilities."""
    cover = row["90% set coverage [%]"]
    if row["method"].startswith(("IDDM", "ProMP")):
        assert row["accuracy [%]"] - 0.1 <= cover <= 100.0
    else:
        assert cover is None


# ------------------------------------------------------------------------------------------
# MSRC-12
# ------------------------------------------------------------------------------------------

PERSONS = ("p01", "p02", "p03", "p04")
GESTURE_IDS = (2, 7, 12)
MOVING_JOINT = {2: 7, 7: 11, 12: 15}  # left hand, right hand, left foot


def separable_positions(gesture: int, rng: np.random.Generator, frames: int = 36) -> np.ndarray:
    """A standing skeleton (anywhere in the room) whose gesture-specific joint is raised by
    0.4 m and oscillates: every single frame tells the gesture apart. ``[frames, 20, 3]``."""
    pose = np.random.default_rng(0).normal(0.0, 0.3, (20, 3))
    t = np.arange(frames)
    pos = pose + rng.normal(0.0, 0.01, (frames, 20, 3)) + rng.uniform(-1, 1, 3) + [0, 0, 3]
    pos[:, MOVING_JOINT[gesture], 1] += 0.4 + 0.1 * np.sin(2 * np.pi * t / 12 + rng.uniform())
    return pos


def write_separable_npz(path: Path, per: int = 3, seed: int = 1) -> None:
    """The development archive's format: ``per`` instances of each gesture and person."""
    rng = np.random.default_rng(seed)
    rows = [(g, p) for p in PERSONS for g in GESTURE_IDS for _ in range(per)]
    np.savez(
        path,
        positions=np.stack([separable_positions(g, rng) for g, _ in rows]).astype(np.float32),
        gesture=np.array([g for g, _ in rows]),
        person=np.array([p for _, p in rows]),
        sequence=np.array([f"P1_1_{g}_{p}" for g, p in rows]),
    )


SMOKE = {"fit_steps": 3, "windows": (4,), "forgettings": (0.2,), "pca": 4}


def check_decisions_and_folds(table, n_persons: int) -> None:
    """Every frame of every test instance is decided once; folds never share a person."""
    folds = table.meta["folds"]
    frames, k = table.meta["frames"], len(table.meta["classes"])
    tested = [p for f in folds for p in f["test persons"]]
    assert sorted(tested) == sorted(set(tested)) and len(tested) == n_persons
    for f in folds:
        assert not set(f["test persons"]) & set(f["train persons"])
        assert len(f["test persons"]) + len(f["train persons"]) == n_persons
    n_test = sum(f["n_test"] for f in folds)
    assert len(table.meta["fits"]) == len(folds)
    assert all(isinstance(fit["converged"], bool) for fit in table.meta["fits"])
    for row in table.rows:
        name = row["method"]
        all_, end = (np.asarray(table.meta[key][name]) for key in ("confusion", "confusion_end"))
        assert all_.shape == end.shape == (k, k)
        assert all_.sum() == n_test * frames and end.sum() == n_test
        per_fold = table.meta["per_fold"][name]
        assert len(per_fold["all"]) == len(folds)
        assert row["accuracy [%]"] == pytest.approx(np.mean(per_fold["all"]), abs=0.06)
        assert row["end accuracy [%]"] == pytest.approx(np.mean(per_fold["end"]), abs=0.06)
        assert row["CPU ms/decision"] > 0
        check_coverage(row)


@SHORT_FITS
def test_msrc12_baselines_separate_a_trivially_separable_set(tmp_path):
    path = tmp_path / "separable.npz"
    write_separable_npz(path)
    table = msrc12_recognition(path, folds=2, subsample=3, train_per_class=4, **SMOKE)
    assert table.meta["classes"] == ["crouch", "bow", "kick"] and table.meta["frames"] == 12
    check_decisions_and_folds(table, len(PERSONS))
    rows = {row["method"]: row for row in table.rows}
    for name in ("SVM n=5", "GPC n=5", "HMM n=5", "ProMP (phase estimated)"):
        assert rows[name]["accuracy [%]"] >= 95.0 and rows[name]["end accuracy [%]"] == 100.0
    assert all(f["n_train"] == 3 * 4 and f["Dz"] == 4 for f in table.meta["folds"])


@SHORT_FITS
def test_msrc12_from_original_recordings_through_the_command_line(tmp_path):
    # two gestures of four persons as csv + tagstream files, cut by load_msrc12_folder
    rng = np.random.default_rng(2)
    data = tmp_path / "recordings"
    data.mkdir()
    t_ms = 1000.0 + 20.0 * np.arange(500)  # 10 s at 50 frames/s
    for p in PERSONS:
        for g in (2, 12):
            pos = separable_positions(g, rng, frames=len(t_ms))
            rows = np.concatenate([pos, np.full((len(t_ms), 20, 1), 2.0)], -1)
            lines = [
                " ".join([f"{t:g}", *map(repr, r.ravel().tolist())])
                for t, r in zip(t_ms, rows, strict=True)
            ]
            (data / f"P1_1_{g}_{p}.csv").write_text("\n".join(lines) + "\n")
            ticks = [round(ms * 49.875) for ms in (4480.0, 8000.0)]
            (data / f"P1_1_{g}_{p}.tagstream").write_text(
                "XQPCTick;Tag\n" + "".join(f"{k};{g}\n" for k in ticks)
            )
    out, fig = tmp_path / "table.json", tmp_path / "confusion.png"
    code = main(
        ["--dataset", "msrc12", "--data", str(data), "--quick", "--out", str(out),
         "--figure", str(fig)]
    )  # fmt: skip
    assert code == 0 and fig.stat().st_size > 0
    saved = json.loads(out.read_text())
    assert saved["meta"]["data"] == str(data) and saved["meta"]["classes"] == ["crouch", "kick"]
    assert len(saved["meta"]["folds"]) == 2


@pytest.mark.skipif(not DEV.is_file(), reason=f"{DEV} (shared development data) absent")
@SHORT_FITS
def test_msrc12_smoke_on_the_development_archive():
    table = msrc12_recognition(
        DEV, folds=2, max_persons=4, train_per_class=2, test_per_class=1, subsample=6, **SMOKE
    )
    assert table.meta["persons"] == 4 and table.meta["frames"] == 6
    assert [row["method"] for row in table.rows] == [
        "IDDM batch n=4", "IDDM online eps=0.2", "SVM n=5", "GPC n=5",
        "ProMP (phase estimated)", "HMM n=5",
    ]  # fmt: skip
    check_decisions_and_folds(table, 4)
    assert all(f["n_test"] == 6 for f in table.meta["folds"])


@pytest.mark.parametrize(
    "argv",
    [
        ["--dataset", "kinect"],
        ["--dataset", "msrc12", "--data", "no/such/file.npz"],
        ["--dataset", "msrc12", "--data", "pyproject.toml"],
        ["--data", "."],
        ["--folds", "3"],
        ["--dataset", "msrc12", "--data", ".", "--folds", "1"],
        ["--dataset", "msrc12", "--data", ".", "--train-per-class", "0"],
        ["--dataset", "msrc12", "--data", ".", "--seed", "-1"],
        ["--state-prior", "uniform"],
        ["--dataset", "msrc12", "--data", ".", "--latent-dim", "0"],
    ],
)
def test_bad_arguments_exit_before_any_work(monkeypatch, capsys, argv):
    def no_work(*args, **kwargs):
        raise AssertionError("the experiment ran despite bad arguments")

    monkeypatch.setattr(ar, "action_recognition", no_work)
    monkeypatch.setattr(ar, "msrc12_recognition", no_work)
    with pytest.raises(SystemExit) as err:
        main(argv)
    assert err.value.code == 2
    assert "usage: hgpdm action-recognition" in capsys.readouterr().err


def test_msrc12_without_data_when_the_default_is_absent(monkeypatch, tmp_path, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(ar, "msrc12_recognition", lambda *a, **k: pytest.fail("ran"))
    with pytest.raises(SystemExit) as err:
        main(["--dataset", "msrc12"])
    assert err.value.code == 2 and "needs --data" in capsys.readouterr().err
