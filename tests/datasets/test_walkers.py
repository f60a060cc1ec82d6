"""Walkers preprocessing: synthetic trajectories with known answers, scipy's rotations as the
oracle for the Euler split (the real trials: test_cmu.py); which of a protocol's trials a folder
holds, from file names alone (empty files: nothing may be read)."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from sklearn.preprocessing import StandardScaler

from hgpdm_torch.datasets import Standardizer, frame_features, motion_features
from hgpdm_torch.datasets.cmu import PROTOCOLS, Protocol
from hgpdm_torch.datasets.mocap import Bone, Skeleton
from hgpdm_torch.datasets.walkers import (
    MissingTrialsError,
    find_trials,
    loto_folds,
    protocol_trials,
    spread_folds,
)


def skeleton(root_order=("tx", "ty", "tz", "rx", "ry", "rz"), angle="deg") -> Skeleton:
    bones = {
        "lfemur": Bone(1, "lfemur", np.zeros(3), 1.0, np.zeros(3), "XYZ", ("rx", "ry", "rz")),
        "ltibia": Bone(2, "ltibia", np.zeros(3), 1.0, np.zeros(3), "XYZ", ("rx",)),
    }
    parent = {"lfemur": "root", "ltibia": "lfemur"}
    return Skeleton("test", {"angle": angle}, tuple(root_order), bones, parent)


def trial(sk: Skeleton, T: int, **columns) -> tuple[np.ndarray, list[str]]:
    """``[T, C]`` values with the given ``root_tx=...`` style columns, zeros elsewhere."""
    channels = sk.channels()
    values = np.zeros((T, len(channels)))
    for key, col in columns.items():
        values[:, channels.index(key.replace("_", "."))] = col
    return values, channels


def column(features, names, name):
    return features[:, names.index(name)]


@pytest.mark.parametrize("heading", [0.0, 90.0, 200.0, -45.0])
def test_straight_walk_has_known_heading_frame_velocity(heading):
    sk = skeleton()
    frames = np.arange(81)
    th = math.radians(heading)
    forward, left = 0.2, 0.05  # per 120 frames/s frame
    x = 3.0 + frames * (forward * math.sin(th) + left * math.cos(th))
    z = -7.0 + frames * (forward * math.cos(th) - left * math.sin(th))
    ty = 17 + np.sin(frames / 5)
    values, channels = trial(sk, 81, root_tx=x, root_ty=ty, root_tz=z, root_ry=heading)
    f, names = motion_features(values, channels, sk, fps=120, target_fps=15)
    assert f.shape == (10, len(channels)) and names[:2] == ["root.vx_heading", "root.vz_heading"]
    np.testing.assert_allclose(column(f, names, "root.vz_heading"), 8 * forward, atol=1e-12)
    np.testing.assert_allclose(column(f, names, "root.vx_heading"), 8 * left, atol=1e-12)
    np.testing.assert_allclose(column(f, names, "root.ty"), ty[::8][1:])
    for name in ("root.yaw_rate", "root.pitch", "root.roll"):
        np.testing.assert_allclose(column(f, names, name), 0.0, atol=1e-12)


@pytest.mark.parametrize("rate", [3.0, -2.5])
def test_turning_gives_the_yaw_rate_across_the_wrap(rate):
    sk = skeleton()
    ry = 150.0 + rate * np.arange(60)  # crosses +-180 degrees either way
    values, channels = trial(sk, 60, root_ry=ry, root_rx=4.0)
    f, names = motion_features(values, channels, sk, fps=30, target_fps=15)
    np.testing.assert_allclose(column(f, names, "root.yaw_rate"), math.radians(2 * rate))
    np.testing.assert_allclose(column(f, names, "root.pitch"), math.radians(4.0), atol=1e-12)


def test_pure_pitch_and_pure_roll():
    sk = skeleton()
    for rx, ry, rz, pitch, roll in [(10, 0, 0, 10, 0), (0, 0, 15, 0, 15), (-20, 120, 0, -20, 0)]:
        values, channels = trial(sk, 3, root_rx=rx, root_ry=ry, root_rz=rz)
        f, names = motion_features(values, channels, sk, fps=30)
        np.testing.assert_allclose(column(f, names, "root.pitch"), math.radians(pitch), atol=1e-12)
        np.testing.assert_allclose(column(f, names, "root.roll"), math.radians(roll), atol=1e-12)
        np.testing.assert_allclose(column(f, names, "root.yaw_rate"), 0.0, atol=1e-12)


@pytest.mark.parametrize("order", [("rx", "ry", "rz"), ("rz", "ry", "rx"), ("ry", "rz", "rx")])
def test_orientation_split_matches_scipy(order):
    """Root angles about fixed axes in the ASF order; scipy composes and decomposes them."""
    rng = np.random.default_rng(0)
    T = 40
    yaw = rng.uniform(-np.pi, np.pi, T)
    pitch = rng.uniform(-1.3, 1.3, T)
    roll = rng.uniform(-np.pi, np.pi, T)
    rot = Rotation.from_euler("YXZ", np.stack([yaw, pitch, roll], 1))  # Ry Rx Rz, intrinsic
    seq = "".join(d[1] for d in order)  # lower case: scipy's fixed (extrinsic) axes
    angles = rot.as_euler(seq, degrees=True)
    sk = skeleton(root_order=("tx", "ty", "tz", *order))
    cols = {f"root_{d}": angles[:, i] for i, d in enumerate(order)}
    values, channels = trial(sk, T, **cols)
    f, names = motion_features(values, channels, sk, fps=30)
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    np.testing.assert_allclose(column(f, names, "root.pitch"), pitch[1:], atol=1e-9)
    np.testing.assert_allclose(wrap(column(f, names, "root.roll") - roll[1:]), 0.0, atol=1e-9)
    np.testing.assert_allclose(
        wrap(column(f, names, "root.yaw_rate") - np.diff(yaw)), 0.0, atol=1e-9
    )


def test_joint_angles_are_wrapped_radians():
    deg = np.array([0.0, 179.0, 180.0, 181.0, 359.0, -181.0, 540.0, -180.0])
    expected = np.radians([179.0, -180.0, -179.0, -1.0, 179.0, -180.0, -180.0])
    sk = skeleton()
    values, channels = trial(sk, len(deg), lfemur_ry=deg, ltibia_rx=deg / 100)
    f, names = motion_features(values, channels, sk, fps=10)
    np.testing.assert_allclose(column(f, names, "lfemur.ry"), expected, atol=1e-12)
    assert np.all(f[:, 6:] >= -np.pi) and np.all(f[:, 6:] < np.pi)
    assert names[6:] == ["lfemur.rx", "lfemur.ry", "lfemur.rz", "ltibia.rx"]
    # radians in the file: no conversion, still wrapped
    sk = skeleton(angle="rad")
    values, channels = trial(sk, 3, ltibia_rx=np.array([0.5, 4.0, -0.5]))
    f, names = motion_features(values, channels, sk, fps=10)
    np.testing.assert_allclose(column(f, names, "ltibia.rx"), [4.0 - 2 * np.pi, -0.5])


def test_resampling_stride_and_channel_order():
    sk = skeleton()
    ty = np.arange(50.0)
    values, channels = trial(sk, 50, root_ty=ty, ltibia_rx=ty)
    f, names = motion_features(values, channels, sk, fps=120, target_fps=30)
    assert f.shape == (12, 10)  # ceil(50 / 4) - 1
    np.testing.assert_allclose(column(f, names, "root.ty"), ty[::4][1:])
    f, _ = motion_features(values, channels, sk, fps=120)
    assert f.shape == (49, 10)
    # channels may come in any order; root channels become the six root features
    perm = np.random.default_rng(1).permutation(len(channels))
    g, gnames = motion_features(values[:, perm], [channels[i] for i in perm], sk, fps=120)
    assert gnames[:6] == names[:6] and sorted(gnames) == sorted(names)
    for name in names:
        np.testing.assert_allclose(column(g, gnames, name), column(f, names, name))


def test_bad_inputs_raise():
    sk = skeleton()
    values, channels = trial(sk, 8)
    with pytest.raises(ValueError, match="channels"):
        motion_features(values, channels[:-1], sk, fps=30)
    with pytest.raises(ValueError, match="channels"):
        motion_features(values[:, 1:], channels[1:], sk, fps=30)  # root.tx missing
    with pytest.raises(ValueError, match="channels"):
        motion_features(values, [*channels[:-1], "rfemur.rx"], sk, fps=30)
    for fps in (0, -30.0, float("nan"), math.inf):
        with pytest.raises(ValueError, match="fps"):
            motion_features(values, channels, sk, fps=fps)
    with pytest.raises(ValueError, match="target_fps"):
        motion_features(values, channels, sk, fps=30, target_fps=0)
    with pytest.raises(ValueError, match="target_fps"):
        motion_features(values, channels, sk, fps=120, target_fps=50)  # stride 2.4
    with pytest.raises(ValueError, match="target_fps"):
        motion_features(values, channels, sk, fps=15, target_fps=30)
    with pytest.raises(ValueError, match="values"):
        motion_features(values[:1], channels, sk, fps=30)
    with pytest.raises(ValueError, match="values"):
        motion_features(np.full_like(values, np.nan), channels, sk, fps=30)
    with pytest.raises(ValueError, match="values"):
        motion_features(values[0], channels, sk, fps=30)
    tilted = skeleton()
    tilted.root_orientation = np.array([0.0, 90.0, 0.0])
    with pytest.raises(ValueError, match="skeleton"):
        motion_features(values, channels, tilted, fps=30)


# ------------------------------------------------------------------------------------------
# Standardizer
# ------------------------------------------------------------------------------------------


def test_standardizer_drops_constant_channels_and_maps_back(generator):
    train = [torch.randn(20, 4, generator=generator) * torch.tensor([1.0, 3.0, 1.0, 0.1])]
    train.append(torch.randn(15, 4, generator=generator))
    for s in train:
        s[:, 2] = 1e6 * (1 + 1e-16 * torch.randn(s.shape[0], generator=generator))  # constant
    st = Standardizer().fit(train)
    assert st.keep_.tolist() == [True, True, False, True]
    assert st.kept(["a", "b", "c", "d"]) == ["a", "b", "d"]
    flat = torch.cat(train)
    ref = StandardScaler().fit(flat[:, [0, 1, 3]].numpy())
    test = torch.randn(3, 7, 4, generator=generator)
    u = st.transform(test)
    assert u.shape == (3, 7, 3)
    np.testing.assert_allclose(
        u.reshape(-1, 3).numpy(), ref.transform(test.reshape(-1, 4)[:, [0, 1, 3]].numpy())
    )
    back = st.inverse_transform(u)
    torch.testing.assert_close(back[..., [0, 1, 3]], test[..., [0, 1, 3]])
    torch.testing.assert_close(back[..., 2], torch.full((3, 7), 1e6))
    # an array of frames works too, and float32 inputs stay float32
    st2 = Standardizer().fit(flat.numpy())
    torch.testing.assert_close(st2.mean_, st.mean_)
    assert st.transform(test.float()).dtype == torch.float32


def test_standardizer_bad_inputs():
    with pytest.raises(ValueError, match="rtol"):
        Standardizer(rtol=-1.0)
    with pytest.raises(ValueError, match="sequences"):
        Standardizer().fit([])
    with pytest.raises(ValueError, match="channels"):
        Standardizer().fit([torch.zeros(3, 2), torch.zeros(3, 4)])
    st = Standardizer().fit([torch.randn(5, 3)])
    with pytest.raises(ValueError, match="z"):
        st.transform(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="u"):
        st.inverse_transform(torch.zeros(2, 4))
    with pytest.raises(ValueError, match="names"):
        st.kept(["a"])
    with pytest.raises(RuntimeError, match="fit"):
        Standardizer().transform(torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"channels \[1\] are missing"):
        Standardizer().fit([torch.tensor([[1.0, float("nan")], [2.0, float("nan")]])])


def test_standardizer_leaves_missing_values_out_and_keeps_them_missing(generator):
    x = torch.randn(20, 3, generator=generator, dtype=torch.float64)
    gappy = x.clone()
    gappy[4:7] = float("nan")  # missing frames
    gappy[10, 1] = float("nan")  # one missing marker coordinate
    st = Standardizer().fit([gappy])
    for c, rows in ((0, [r for r in range(20) if r not in (4, 5, 6)]),
                    (1, [r for r in range(20) if r not in (4, 5, 6, 10)])):  # fmt: skip
        ref = Standardizer().fit([x[rows, c : c + 1]])
        torch.testing.assert_close(st.mean_[c : c + 1], ref.mean_)
        torch.testing.assert_close(st.scale_[c : c + 1], ref.scale_)
    out = st.transform(gappy)
    assert out[4:7].isnan().all() and out[10, 1].isnan() and out[10, [0, 2]].isfinite().all()


# ------------------------------------------------------------------------------------------
# Features of consecutive frames
# ------------------------------------------------------------------------------------------


def test_frame_features_are_frames_beside_numpy_differences_or_lags(generator):
    z = torch.randn(3, 6, 4, generator=generator, dtype=torch.float64)
    torch.testing.assert_close(frame_features(z, "frames"), z, rtol=0, atol=0)
    v, lag = frame_features(z, "velocity"), frame_features(z, "lagged")
    assert v.shape == lag.shape == (3, 5, 8)
    for f in (v, lag):
        np.testing.assert_array_equal(f[..., :4].numpy(), z[:, 1:].numpy())
    np.testing.assert_allclose(v[..., 4:].numpy(), np.diff(z.numpy(), axis=1), rtol=0, atol=0)
    np.testing.assert_array_equal(lag[..., 4:].numpy(), z[:, :-1].numpy())
    # a missing frame spoils its own row and the next row's second half, nothing else
    z[1, 2] = float("nan")
    for kind in ("velocity", "lagged"):
        f = frame_features(z, kind)
        assert torch.isnan(f).any(-1).nonzero().tolist() == [[1, 1], [1, 2]]
        assert torch.isnan(f[1, 1, :4]).all()
        assert torch.isnan(f[1, 2, 4:]).all() and not torch.isnan(f[1, 2, :4]).any()
        # one sequence [T, D] works the same way
        torch.testing.assert_close(frame_features(z[0], kind), f[0], equal_nan=True)


def test_frame_features_bad_inputs():
    with pytest.raises(ValueError, match="at least 2 frames"):
        frame_features(torch.zeros(1, 3), "velocity")
    assert frame_features(torch.zeros(1, 3), "frames").shape == (1, 3)
    with pytest.raises(ValueError, match="z"):
        frame_features(torch.zeros(3), "lagged")
    with pytest.raises(ValueError, match="kind"):
        frame_features(torch.zeros(2, 3), "speed")


def touch(folder, *names):
    """Empty files: the trial search looks at names only (reading one would fail)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_text("")
    return folder


def test_found_trials_per_label_with_the_absent_files_named(tmp_path):
    walkers = PROTOCOLS["walkers"]
    data = touch(tmp_path / "data", "07.asf", "07_01.amc", "07_02.amc", "16_15.amc", "16_16.amc")
    found = find_trials(walkers, "train", data, source="--data D")
    assert found.trials == ["07_01", "07_02"]
    assert found.missing_trials == [t for t, _ in walkers.train if t not in ("07_01", "07_02")]
    assert found.describe() == (
        "training trials from --data D: subject 07: 07_01, 07_02 (07_03 missing); subject 08: "
        "none (08_01, 08_02, 08_03 missing); subject 16: none (16_15, 16_16 missing: no 16.asf); "
        "subject 35: none (35_01, 35_02, 35_03 missing)"
    )
    found.require("any")
    want = (
        "--data D: no training trial for subject 08 (expected one of 08_01.amc, 08_02.amc, "
        "08_03.amc with 08.asf); subject 16 (expected one of 16_15.amc, 16_16.amc with 16.asf)"
    )
    with pytest.raises(MissingTrialsError, match=re.escape(want)) as err:
        found.require("every label")
    assert isinstance(err.value, FileNotFoundError) and isinstance(err.value, ValueError)
    with pytest.raises(MissingTrialsError, match="absent: 07_03.amc, 08_01.amc.*16.asf, 35_01"):
        found.require("all")
    with pytest.raises(ValueError, match="need must be"):
        found.require("most")
    # an empty folder: every trial expected, nothing read
    empty = find_trials(walkers, "train", touch(tmp_path / "empty"))
    assert empty.trials == [] and empty.source == str(tmp_path / "empty")
    with pytest.raises(MissingTrialsError, match=r"no walkers training trial \(expected one of "):
        empty.require("any")
    # the test split; a skeleton from a second folder; a missing folder
    test = find_trials(walkers, "test", touch(tmp_path / "test", "16_22.amc"), skeletons=[data])
    assert test.trials == [] and test.missing[-8] == ("16_22", "16", "16.asf")
    touch(data, "16.asf")
    test = find_trials(walkers, "test", tmp_path / "test", skeletons=[data])
    assert test.trials == ["16_22"] and test.split == "test"
    assert "subject 16: 16_22;" in test.describe()
    with pytest.raises(FileNotFoundError, match="not found"):
        find_trials(walkers, "train", tmp_path / "absent")


MINE = Protocol(
    "mine",
    "subject",
    ("01", "02"),
    (("01_01", "01"), ("01_02", "01"), ("02_01", "02"), ("02_02", "02")),
    (("01_09", "01"), ("02_09", "02")),
    10,
    "none",
)


def test_a_forecasting_run_needs_every_label_and_takes_test_trials_from_their_folder(tmp_path):
    data = touch(tmp_path / "data", "01.asf", "02.asf", "01_01.amc", "01_02.amc", "02_01.amc")
    train, test = protocol_trials(MINE, data)
    assert train.trials == ["01_01", "01_02", "02_01"] and test is None
    # the test trials lie in the training folder only: never taken from there
    touch(data, "01_09.amc", "02_09.amc")
    empty = touch(tmp_path / "empty")
    names = ("--data", "--test-data")
    want = f"--test-data {empty}: no mine test trial (expected one of 01_09.amc, 02_09.amc"
    with pytest.raises(MissingTrialsError, match=re.escape(want)):
        protocol_trials(MINE, data, empty, names)
    touch(tmp_path / "test", "02_09.amc")  # its skeleton from the training folder
    _, test = protocol_trials(MINE, data, tmp_path / "test", names)
    assert test.trials == ["02_09"] and test.missing_trials == ["01_09"]
    assert test.describe().startswith(f"test trials from --test-data {tmp_path / 'test'}: ")
    # a label without a training trial
    (data / "02_01.amc").unlink()
    want = "no training trial for subject 02 (expected one of 02_01.amc, 02_02.amc with 02.asf)"
    with pytest.raises(MissingTrialsError, match=re.escape(want)):
        protocol_trials(MINE, data)
    # CV with one trial per label holds nothing out; each fit's baselines need two trials
    (data / "01_02.amc").unlink()
    touch(data, "02_01.amc")
    with pytest.raises(MissingTrialsError, match="needs a subject with two training trials"):
        protocol_trials(MINE, data)
    one = Protocol("one", "style", ("a",), (("01_01", "a"), ("01_02", "a")), (), 10, "none")
    with pytest.raises(MissingTrialsError, match="CV needs at least 3"):
        protocol_trials(one, touch(data, "01_02.amc"))


def test_leave_one_trial_out_folds_spread_over_the_labels():
    folds, untestable = loto_folds([0, 0, 1, 1, 1, 2])
    assert untestable == [5]

    class Data:
        labels = torch.tensor([0, 0, 1, 1, 1, 2])

    assert [held for _, held in spread_folds(folds, Data, 3)] == [[0], [1], [2]]
    assert spread_folds(folds, Data, None) == folds
