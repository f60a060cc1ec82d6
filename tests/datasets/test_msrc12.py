"""MSRC-12 loaders and Kinect features.

The original-format reader is checked on small csv/tagstream files written here with known
positions and action points; the development archive on the shared file, skipped when absent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import (
    MissingTagstreamError,
    PosePCA,
    kinect_features,
    load_msrc12_folder,
    load_msrc12_npz,
    read_msrc12_recording,
)
from hgpdm_torch.datasets.msrc12 import JOINTS, TICKS_PER_SECOND

DEV = Path("../shared/data/msrc12_dev.npz")
needs_dev = pytest.mark.skipif(not DEV.is_file(), reason=f"{DEV} (shared development data) absent")


def tick(ms: float) -> int:
    """The tagstream tick of a time in ms (exact for multiples of 8 ms: 49875 * 8 / 1000)."""
    value = ms * TICKS_PER_SECOND / 1000
    assert value == int(value)
    return int(value)


def write_recording(
    folder: Path,
    name: str,
    time_ms: np.ndarray,
    positions: np.ndarray,
    tags: list[str],
    *,
    sep: str = " ",
    header: str | None = "XQPCTick;Tag",
) -> Path:
    """Write ``<name>.csv`` (timestamp, then x y z w of 20 joints per line) and its tagstream."""
    w = np.full(positions.shape[:2] + (1,), 2.0)
    rows = np.concatenate([positions, w], -1).reshape(len(time_ms), -1)
    lines = [
        sep.join([f"{t:g}", *(repr(float(v)) for v in row)])
        for t, row in zip(time_ms, rows, strict=True)
    ]
    csv = folder / f"{name}.csv"
    csv.write_text("\n".join(lines) + "\n")
    text = ([header] if header else []) + tags
    (folder / f"{name}.tagstream").write_text("\n".join(text) + "\n")
    return csv


def random_positions(frames: int, seed: int = 0) -> np.ndarray:
    """Positions rounded to 6 decimals, as in the real files (exact after a text round trip)."""
    rng = np.random.default_rng(seed)
    return np.round(rng.normal(0.0, 0.5, (frames, len(JOINTS), 3)) + [0, 0, 3], 6)


# ------------------------------------------------------------------------------------------
# Original format: recordings and windows
# ------------------------------------------------------------------------------------------


def test_window_is_cut_exactly_around_the_action_point(tmp_path):
    # frames every 20 ms from 1000 ms, action point at 4000 ms: the 10 frames/s samples
    # 1000, 1100, ..., 4500 ms fall on every 5th csv frame
    t = 1000.0 + 20.0 * np.arange(300)  # 1000 .. 6980 ms
    pos = random_positions(len(t))
    write_recording(tmp_path, "P1_1_12A_p21", t, pos, [f"{tick(4000)};12"])
    rec = read_msrc12_recording(tmp_path / "P1_1_12A_p21.csv")
    assert rec.tag_ms.tolist() == [4000.0] and rec.tag_gesture.tolist() == [12]
    assert (rec.instruction, rec.gesture, rec.variant, rec.person) == ("P1_1", 12, "A", "p21")
    np.testing.assert_array_equal(rec.positions, pos)
    np.testing.assert_array_equal(rec.state, 2.0)
    for method in ("linear", "nearest"):
        data = load_msrc12_folder(tmp_path, fps=10, before=3.0, after=0.5, method=method)
        assert data.positions.shape == (1, 36, 20, 3) and data.action_frame == 30
        np.testing.assert_array_equal(data.positions[0].numpy(), pos[0:180:5])
        np.testing.assert_array_equal(data.positions[0, 30].numpy(), pos[150])  # 4000 ms
        assert data.gesture_ids == (12,) and data.names == ("kick",)
        assert data.labels.tolist() == [0] and data.person == ["p21"]
        assert data.sequence == ["P1_1_12A_p21"] and data.dropped == []


def test_tick_clock_matches_the_csv_milliseconds(tmp_path):
    # an action point between two csv frames
    t = 1000.0 + 20.0 * np.arange(300)
    pos = random_positions(len(t), seed=1)
    write_recording(tmp_path, "P2_1_3_p05", t, pos, [f"{tick(4008)};3"])
    rec = read_msrc12_recording(tmp_path / "P2_1_3_p05.csv")
    assert rec.tag_ms[0] == pytest.approx(tick(4008) * 1000 / 49875) and rec.tag_ms[0] == 4008.0
    data = load_msrc12_folder(tmp_path, fps=10, before=0.2, after=0.1)
    # 4008 ms is 0.4 of the way from the frame at 4000 ms to the one at 4020 ms
    expected = 0.6 * pos[150] + 0.4 * pos[151]
    np.testing.assert_allclose(data.positions[0, 2].numpy(), expected, rtol=0, atol=1e-12)
    assert data.positions.shape[1] == 4 and data.action_frame == 2


def test_resampling_of_irregular_frames(tmp_path):
    # Kinect-like spacing (33/34 ms); positions linear in time are reproduced exactly by linear
    # interpolation, and "nearest" picks the frame with the closest timestamp
    t = np.cumsum(np.r_[500.0, np.tile([33.0, 34.0, 33.0], 100)])
    slope = np.random.default_rng(2).normal(size=(20, 3))
    pos = np.round(1e-3 * t[:, None, None] * slope + 1.0, 6)
    write_recording(tmp_path, "P1_2_6_p09", t, pos, [f"{tick(6000)};6", f"{tick(8000)};6"])
    linear = load_msrc12_folder(tmp_path, fps=15, before=2.0, after=0.6)
    nearest = load_msrc12_folder(tmp_path, fps=15, before=2.0, after=0.6, method="nearest")
    assert linear.positions.shape == (2, 40, 20, 3) and linear.action_frame == 30
    for i, a in enumerate((6000.0, 8000.0)):
        samples = a + (np.arange(40) - 30) * 1000 / 15
        truth = np.round(1e-3 * samples[:, None, None] * slope + 1.0, 6)
        np.testing.assert_allclose(linear.positions[i].numpy(), truth, atol=2e-6)
        near = np.abs(t[None, :] - samples[:, None]).argmin(1)
        np.testing.assert_array_equal(nearest.positions[i].numpy(), pos[near])
    assert linear.person == ["p09", "p09"] and linear.labels.tolist() == [0, 0]


def test_folder_codes_gestures_persons_and_drops_windows(tmp_path):
    t = 1000.0 + 20.0 * np.arange(400)  # 1000 .. 8980 ms
    gap = np.r_[t[:200], t[215:]]  # 300 ms without a tracked frame after 4980 ms
    write_recording(
        tmp_path, "P1_1_8_p14", t, random_positions(len(t), 3),
        [f"{tick(2000)};8", f"{tick(5000)};8", f"{tick(8800)};8"],
    )  # fmt: skip
    write_recording(
        tmp_path, "P3_1_2_p04", gap, random_positions(len(gap), 4),
        [f"{tick(4400)};G2", f"{tick(7000)};G2", f"{tick(8000)};2"], sep=",",
    )  # fmt: skip
    data = load_msrc12_folder(tmp_path)
    # p14: the window of 2000 ms starts before the recording, that of 8800 ms ends after it;
    # p04: the windows of 7000 ms (4000-7500 ms) and 8000 ms (from 5000 ms) span the gap
    assert data.sequence == ["P1_1_8_p14", "P3_1_2_p04"]
    assert data.gesture_ids == (2, 8) and data.names == ("crouch", "throw")
    assert data.labels.tolist() == [1, 0] and data.person == ["p14", "p04"]
    assert data.persons == ["p04", "p14"] and data.groups().tolist() == [1, 0]
    assert len(data.dropped) == 4
    assert sum("outside the recording" in d for d in data.dropped) == 2
    assert sum("gap" in d for d in data.dropped) == 2
    loose = load_msrc12_folder(tmp_path, max_gap=0.5)
    assert len(loose) == 4
    only = load_msrc12_folder(tmp_path, gestures=[8])
    assert only.gesture_ids == (8,) and only.labels.tolist() == [0]
    sub = loose.subset([2, 0])
    assert sub.sequence == [loose.sequence[2], loose.sequence[0]]
    torch.testing.assert_close(sub.positions[1], loose.positions[0])


def test_untracked_frames_are_dropped(tmp_path):
    t = 1000.0 + 20.0 * np.arange(300)
    pos = random_positions(len(t), 5)
    pos[:10] = 0.0  # no skeleton yet
    write_recording(tmp_path, "P1_1_7_p10", t, pos, [f"{tick(5000)};7"])
    rec = read_msrc12_recording(tmp_path / "P1_1_7_p10.csv")
    assert rec.untracked == 10 and rec.time_ms[0] == 1200.0 and len(rec.time_ms) == 290


def test_frames_with_a_lost_joint_are_refused_or_dropped(tmp_path):
    """A joint at (0, 0, 0) while the others are tracked is never read as a position (issue 54):
    an error naming the frame and joint, or, when asked, the frame is dropped like an untracked
    one and the window interpolated across it."""
    t = 1000.0 + 20.0 * np.arange(300)
    pos = random_positions(len(t), 6)
    pos[100:103, JOINTS.index("wrist_left")] = 0.0  # 3000-3040 ms
    csv = write_recording(tmp_path, "P1_1_7_p11", t, pos, [f"{tick(4000)};7"])
    with pytest.raises(ValueError, match=r"P1_1_7_p11\.csv, line 101 \(frame 101\): joint "
                       r"'wrist_left' is at \(0, 0, 0\)"):  # fmt: skip
        read_msrc12_recording(csv)
    with pytest.raises(ValueError, match=r"line 101 \(frame 101\): joint 'wrist_left'"):
        load_msrc12_folder(tmp_path)
    rec = read_msrc12_recording(csv, partial_frames="drop")
    assert rec.untracked == rec.partial == 3 and len(rec.time_ms) == 297
    assert 3000.0 not in rec.time_ms and (rec.positions != 0).any(-1).all()
    data = load_msrc12_folder(tmp_path, partial_frames="drop")
    # the window's sample at 3000 ms lies between the frames at 2980 and 3060 ms
    np.testing.assert_allclose(
        data.positions[0, 20].numpy(), 0.75 * pos[99] + 0.25 * pos[103], atol=1e-12
    )
    for bad in ("skip", None):
        with pytest.raises(ValueError, match="partial_frames"):
            read_msrc12_recording(csv, partial_frames=bad)
        with pytest.raises(ValueError, match="partial_frames"):
            load_msrc12_folder(tmp_path, partial_frames=bad)


def test_unparsed_file_name(tmp_path):
    t = 1000.0 + 20.0 * np.arange(300)
    write_recording(tmp_path, "session", t, random_positions(len(t)), [f"{tick(5000)};7"])
    rec = read_msrc12_recording(tmp_path / "session.csv")
    assert rec.person is None and rec.gesture is None and rec.instruction is None
    with pytest.raises(ValueError, match=r"session\.csv.*person"):
        load_msrc12_folder(tmp_path)


def good_lines(frames: int = 5) -> list[str]:
    return [" ".join([str(1000 + 33 * k)] + ["0.5"] * 80) for k in range(frames)]


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda ls: ls.__setitem__(2, ls[2] + " 1.0"),
         r"line 3 \(frame 3\): expected 81 numbers.*got 82"),
        (lambda ls: ls.__setitem__(1, ls[1].rsplit(" ", 1)[0]),
         r"line 2 \(frame 2\): expected 81.*got 80"),
        (lambda ls: ls.__setitem__(1, ls[1].replace("0.5", "abc", 1)),
         r"line 2 \(frame 2\): value 2 \(joint 'hip_centre' x\) is 'abc', not a number"),
        (lambda ls: ls.__setitem__(3, ls[3].replace("0.5", "nan", 1)),
         r"line 4 \(frame 4\): value 2 \(joint 'hip_centre' x\) is nan"),
        (lambda ls: ls.__setitem__(4, ls[4].replace("0.5", "inf", 1)),
         r"line 5 \(frame 5\): value 2 \(joint 'hip_centre' x\) is inf"),
        (lambda ls: ls.__setitem__(4, " ".join(ls[4].split()[:42] + ["-inf"] + ["0.5"] * 38)),
         r"line 5 \(frame 5\): value 43 \(joint 'wrist_right' y\) is -inf"),
        (lambda ls: ls.__setitem__(2, ls[2].replace("1066", "nan", 1)),
         r"line 3 \(frame 3\): value 1 \(the timestamp\) is nan"),
        (lambda ls: ls.__setitem__(3, ls[1]),
         r"line 4 \(frame 4\): timestamp 1033 ms does not increase"),
        # a joint beyond any room (issue 54), and a joint the Kinect lost in a tracked frame
        (lambda ls: ls.__setitem__(1, ls[1].replace("0.5", "-1e6", 3)),
         r"line 2 \(frame 2\): joint 'hip_centre' x is -1e\+06 m; coordinates beyond \+-100 m"),
        (lambda ls: ls.__setitem__(2, " ".join(ls[2].split()[:-4] + ["0.5", "0.5", "250.5", "2"])),
         r"line 3 \(frame 3\): joint 'foot_right' z is 250.5 m"),
        (lambda ls: ls.__setitem__(3, " ".join(ls[3].split()[:25] + ["0", "0", "0"]
                                             + ls[3].split()[28:])),
         r"line 4 \(frame 4\): joint 'wrist_left' is at \(0, 0, 0\), the Kinect's mark of a "
         r"joint it did not track"),
        (lambda ls: ls.clear(), r"is empty"),
        (lambda ls: ls.__setitem__(slice(None), [ln.split(" ", 1)[0] + " 0" * 80 for ln in ls]),
         r"no tracked frame"),
    ],
)  # fmt: skip
def test_malformed_csv(tmp_path, edit, match):
    lines = good_lines()
    edit(lines)
    csv = tmp_path / "P1_1_1_p01.csv"
    csv.write_text("\n".join(lines) + ("\n" if lines else ""))
    (tmp_path / "P1_1_1_p01.tagstream").write_text(f"XQPCTick;Tag\n{tick(1064)};1\n")
    with pytest.raises(ValueError, match=match) as err:
        read_msrc12_recording(csv)
    assert "P1_1_1_p01.csv" in str(err.value)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("XQPCTick;Tag\n53000;1\n53100\n", r"line 3: expected '<tick>;<gesture id>'"),
        ("XQPCTick;Tag\n53000.5;1\n", r"line 2: expected"),
        ("XQPCTick;Tag\n-5;1\n", r"line 2: expected"),
        ("XQPCTick;Tag\n53000;kick\n", r"line 2: expected"),
        ("XQPCTick;Tag\n53000;13\n", r"line 2: gesture id 13 is not in 1-12"),
        ("XQPCTick;Tag;Extra\n53000;1\n", r"line 1: expected a header"),
        ("XQPCTick;Tag\n", r"no action points"),
        ("", r"no action points"),
    ],
)
def test_malformed_tagstream(tmp_path, text, match):
    csv = tmp_path / "P1_1_1_p01.csv"
    csv.write_text("\n".join(good_lines()) + "\n")
    (tmp_path / "P1_1_1_p01.tagstream").write_text(text)
    with pytest.raises(ValueError, match=match) as err:
        read_msrc12_recording(csv)
    assert "P1_1_1_p01.tagstream" in str(err.value)


def test_tagstream_without_header_is_read(tmp_path):
    csv = tmp_path / "P1_1_1_p01.csv"
    csv.write_text("\n".join(good_lines()) + "\n")
    (tmp_path / "P1_1_1_p01.tagstream").write_text(f"{tick(1064)};1\n\n{tick(1096)};G1\n")
    rec = read_msrc12_recording(csv)
    assert rec.tag_ms.tolist() == [1064.0, 1096.0]


def test_missing_files_and_inconsistent_recordings(tmp_path):
    csv = tmp_path / "P1_1_1_p01.csv"
    csv.write_text("\n".join(good_lines()) + "\n")
    with pytest.raises(MissingTagstreamError, match=r"P1_1_1_p01\.csv has no tagstream") as err:
        read_msrc12_recording(csv)
    assert isinstance(err.value, ValueError) and isinstance(err.value, FileNotFoundError)
    with pytest.raises(MissingTagstreamError):
        load_msrc12_folder(tmp_path)
    with pytest.raises(FileNotFoundError, match="not found"):
        read_msrc12_recording(tmp_path / "absent.csv")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no MSRC-12 recording"):
        load_msrc12_folder(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="folder not found"):
        load_msrc12_folder(tmp_path / "absent")
    # the tag's gesture must agree with the file name's
    (tmp_path / "P1_1_1_p01.tagstream").write_text(f"XQPCTick;Tag\n{tick(1064)};2\n")
    with pytest.raises(ValueError, match=r"action point 1 has gesture id 2, the file name says 1"):
        load_msrc12_folder(tmp_path)
    # action points outside the csv's time span: a different tick clock
    (tmp_path / "P1_1_1_p01.tagstream").write_text("XQPCTick;Tag\n64000;1\n")
    with pytest.raises(ValueError, match=r"none of its 1 action points.*49875 Hz"):
        load_msrc12_folder(tmp_path)


def test_window_arguments(tmp_path):
    with pytest.raises(ValueError, match="fps"):
        load_msrc12_folder(tmp_path, fps=0)
    with pytest.raises(ValueError, match="whole number of frames"):
        load_msrc12_folder(tmp_path, fps=10, before=0.25)
    with pytest.raises(ValueError, match="before"):
        load_msrc12_folder(tmp_path, before=-1.0)
    with pytest.raises(ValueError, match="method"):
        load_msrc12_folder(tmp_path, method="cubic")
    with pytest.raises(ValueError, match="max_gap"):
        load_msrc12_folder(tmp_path, max_gap=0)


# ------------------------------------------------------------------------------------------
# Features and statistics
# ------------------------------------------------------------------------------------------


def test_kinect_features_are_hip_relative():
    pos = torch.as_tensor(random_positions(12, 6)).reshape(2, 6, 20, 3)
    f = kinect_features(pos)
    assert f.shape == (2, 6, 57) and f.dtype == torch.float64
    torch.testing.assert_close(f[1, 4, :3], pos[1, 4, 1] - pos[1, 4, 0])
    torch.testing.assert_close(f[0, 2, -3:], pos[0, 2, 19] - pos[0, 2, 0])
    shifted = kinect_features(pos + torch.tensor([0.3, -1.0, 2.0]))
    torch.testing.assert_close(shifted, f)
    full = kinect_features(pos, include_hip=True)
    assert full.shape == (2, 6, 60) and bool((full[..., :3] == 0).all())
    torch.testing.assert_close(full[..., 3:], f)
    hands = kinect_features(pos, ["hand_left", 11])
    torch.testing.assert_close(hands, torch.cat([f[..., 18:21], f[..., 30:33]], -1))
    for bad in (["elbow"], [20], [3, 3], []):
        with pytest.raises(ValueError, match="joints"):
            kinect_features(pos, bad)
    with pytest.raises(ValueError, match=r"\[\.\.\., T, 20, 3\]"):
        kinect_features(pos[..., :2])


def test_pose_pca_uses_training_frames_only():
    gen = torch.Generator().manual_seed(0)
    scale = torch.diag(torch.tensor([3.0, 2, 1, 0.5, 0, 0.1]))
    train = torch.randn(30, 8, 6, generator=gen) @ scale
    test = torch.randn(5, 8, 6, generator=gen) + 4.0
    pca = PosePCA(3).fit(train)
    frames = train.reshape(-1, 6)
    # oracle: SVD of the centred training frames
    centred = frames - frames.mean(0)
    _, s, vt = torch.linalg.svd(centred, full_matrices=False)
    u_train = pca.transform(train)
    assert u_train.shape == (30, 8, 3) and pca.dim_ == 3
    torch.testing.assert_close(u_train.reshape(-1, 3).mean(0), torch.zeros(3), atol=1e-12, rtol=0)
    torch.testing.assert_close(u_train.reshape(-1, 3).abs(), (centred @ vt[:3].T).abs())
    torch.testing.assert_close(
        torch.tensor(pca.explained_variance_ratio_), s[:3] ** 2 / (s**2).sum()
    )
    # the test frames are mapped with the training mean, not their own
    torch.testing.assert_close(
        pca.transform(test).reshape(-1, 3).abs(),
        ((test.reshape(-1, 6) - frames.mean(0)) @ vt[:3].T).abs(),
    )
    assert PosePCA(0.85).fit(train).dim_ == 2  # variances 9 + 4 of 14.26
    plain = PosePCA(None, standardize=True).fit(train)
    out = plain.transform(train).reshape(-1, 5)  # the constant channel is dropped
    torch.testing.assert_close(out.std(0, correction=0), torch.ones(5))
    for bad in (0, 1.5, "3"):
        with pytest.raises(ValueError, match="dim"):
            PosePCA(bad)
    with pytest.raises(RuntimeError, match="fit"):
        PosePCA(2).transform(test)
    with pytest.raises(ValueError, match="6 features"):
        pca.transform(test[..., :5])


# ------------------------------------------------------------------------------------------
# The development archive
# ------------------------------------------------------------------------------------------


def test_npz_errors(tmp_path):
    path = tmp_path / "dev.npz"
    base = {
        "positions": np.full((3, 36, 20, 3), 0.5, np.float32),
        "gesture": np.array([2, 3, 2]),
        "person": np.array(["p01", "p02", "p01"]),
        "sequence": np.array(["a", "b", "c"]),
    }
    far, lost = base["positions"].copy(), base["positions"].copy()
    far[2, 7, JOINTS.index("head"), 1] = 1e6
    lost[1, 35, JOINTS.index("foot_left")] = 0.0
    np.savez(path, **base)
    data = load_msrc12_npz(path)
    assert data.labels.tolist() == [0, 1, 0] and data.names == ("crouch", "push right")
    for change, match in (
        ({"gesture": np.array([2, 3, 13])}, "unknown gesture ids"),
        ({"positions": np.zeros((3, 36, 19, 3))}, r"\[n, T, 20, 3\]"),
        ({"person": np.array(["p01", "p02"])}, "person must be"),
        ({"positions": np.full((3, 36, 20, 3), np.nan)}, "NaN"),
        # a joint beyond any room, one the Kinect lost (issue 54), and no skeleton at all
        (
            {"positions": far},
            r"instance 2, frame 7: joint 'head' y is 1e\+06 m; coordinates "
            r"beyond \+-100 m",
        ),
        ({"positions": lost}, r"instance 1, frame 35: joint 'foot_left' is at \(0, 0, 0\)"),
        ({"positions": np.zeros((3, 36, 20, 3))}, r"instance 0, frame 0: joint 'hip_centre' is at"),
    ):
        np.savez(path, **{**base, **change})
        with pytest.raises(ValueError, match=match):
            load_msrc12_npz(path)
    np.savez(path, positions=base["positions"])
    with pytest.raises(ValueError, match="lacks"):
        load_msrc12_npz(path)
    with pytest.raises(FileNotFoundError):
        load_msrc12_npz(tmp_path / "absent.npz")


@needs_dev
def test_development_archive():
    data = load_msrc12_npz()
    n = len(data)
    assert data.positions.shape == (n, 36, 20, 3) and data.positions.dtype == torch.float64
    assert data.gesture_ids == (2, 3, 6, 7, 8, 12)
    assert data.names == ("crouch", "push right", "shoot", "bow", "throw", "kick")
    assert sorted(data.labels.unique().tolist()) == list(range(6))
    assert len(data.persons) == 20 and data.action_frame == 30 and data.fps == 10.0
    groups = data.groups()
    assert groups.shape == (n,) and set(groups.tolist()) == set(range(20))
    # each recording is one person performing one gesture
    for seq in set(data.sequence[:: max(1, n // 40)]):
        idx = [i for i, s in enumerate(data.sequence) if s == seq]
        assert len({data.person[i] for i in idx}) == 1
        assert len({int(data.labels[i]) for i in idx}) == 1
        assert seq.endswith(data.person[idx[0]])
    f = kinect_features(data.positions)
    assert f.shape == (n, 36, 57)
    # hip-relative joints of a standing person lie within ~1.2 m of the hip centre
    assert float(f.abs().max()) < 1.5


@needs_dev
def test_development_pca_from_training_persons():
    data = load_msrc12_npz()
    groups = data.groups()
    train = groups >= 5
    f = kinect_features(data.positions)
    pca = PosePCA(0.95).fit(f[train])
    assert 3 <= pca.dim_ <= 30 and sum(pca.explained_variance_ratio_) >= 0.95
    z = pca.transform(f)
    assert z.shape == (len(data), 36, pca.dim_)
    torch.testing.assert_close(
        z[train].reshape(-1, pca.dim_).mean(0), torch.zeros(pca.dim_), atol=1e-9, rtol=0
    )
