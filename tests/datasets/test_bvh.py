"""BVH loader on small files written here: values read back as written, the CMU loader's
features (checked against bvhio's own rotations), and every refusal."""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import MAX_ANGLE_DEGREES, MotionTrials, load_bvh, read_bvh
from hgpdm_torch.datasets.walkers import ROOT_FEATURES

bvhio = pytest.importorskip("bvhio", reason="the BVH loader needs bvhio (the data extra)")
glm = pytest.importorskip("glm", reason="bvhio's rotations are glm's (pyglm, with bvhio)")

ROOT = "Xposition Yposition Zposition Zrotation Xrotation Yrotation"


def _hierarchy(root_channels: str = ROOT, *, leg: str = "LeftLeg") -> str:
    count = len(root_channels.split())
    return f"""HIERARCHY
ROOT Hips
{{
  OFFSET 0.0 0.0 0.0
  CHANNELS {count} {root_channels}
  JOINT LeftUpLeg
  {{
    OFFSET 10.5 -5.25 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT {leg}
    {{
      OFFSET 0.0 -40.0 0.0
      CHANNELS 1 Xrotation
      End Site
      {{
        OFFSET 0.0 -40.0 0.0
      }}
    }}
  }}
  JOINT Spine
  {{
    OFFSET 0.0 8.0 0.0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {{
      OFFSET 0.0 10.0 0.0
    }}
  }}
}}
"""


def _values(frames: int, root: int = 6, seed: int = 0) -> np.ndarray:
    """``[frames, root + 7]``: a walk forward while turning, with joint angles beyond 180."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames)
    cols = []
    if root == 6:
        cols += [3 * np.sin(0.1 * t), 90 + np.cos(0.3 * t), 2.5 * t]  # positions
    cols += [5 * np.sin(0.2 * t), 10 * np.cos(0.25 * t), 4 * t + 7]  # root Z X Y rotation
    cols += [list(rng.uniform(-250, 250, frames)) for _ in range(7)]
    return np.round(np.stack(cols, 1), 6)


def _write(
    path: Path,
    values: np.ndarray,
    *,
    hierarchy: str | None = None,
    ft="0.008333333",
    frames: int | None = None,
    crlf: bool = False,
) -> Path:
    lines = [
        hierarchy or _hierarchy(),
        "MOTION",
        f"Frames: {frames or len(values)}",
        f"Frame Time: {ft}",
    ] + [" ".join(repr(float(v)) for v in row) for row in values]
    path.write_bytes(("\n".join(lines) + "\n").replace("\n", "\r\n" if crlf else "\n").encode())
    return path


def _wrap(x: np.ndarray) -> np.ndarray:
    return (x + np.pi) % (2 * np.pi) - np.pi


def test_channels_read_back_as_written_crlf_like_lf(tmp_path):
    """A file written here reads back equal: every channel as written (degrees beyond 180
    kept, unlike bvhio's own keyframes), then in radians, named, at the file's rate."""
    values = _values(11)
    _write(tmp_path / "a.bvh", values)
    _write(tmp_path / "b.bvh", values, crlf=True)
    motion = read_bvh(tmp_path / "b.bvh")
    np.testing.assert_array_equal(motion.values, values)
    assert motion.channels == [
        "root.tx",
        "root.ty",
        "root.tz",
        "root.rz",
        "root.rx",
        "root.ry",
        "LeftUpLeg.rz",
        "LeftUpLeg.rx",
        "LeftUpLeg.ry",
        "LeftLeg.rx",
        "Spine.rz",
        "Spine.rx",
        "Spine.ry",
    ]
    sk = motion.skeleton
    assert sk.root == "Hips" and sk.parent == {
        "LeftUpLeg": "Hips",
        "LeftLeg": "LeftUpLeg",
        "Spine": "Hips",
    }
    np.testing.assert_allclose(sk.offsets["LeftUpLeg"], [10.5, -5.25, 0.0])
    assert motion.fps == 1 / 0.008333333
    data = load_bvh(tmp_path, features="channels", downsample=3)
    assert isinstance(data, MotionTrials)
    assert data.trials == ["a", "b"] and data.label_names == (tmp_path.name,)
    assert data.labels.tolist() == [0, 0] and data.missing == []
    assert data.features == motion.channels and data.fps == 1 / 0.008333333 / 3
    rotation = np.array([c.split(".")[1].startswith("r") for c in motion.channels])
    want = np.where(rotation, _wrap(np.deg2rad(values)), values)[::3]  # rows 0 3 6 9
    for seq in data.sequences:
        assert seq.dtype == torch.float64 and seq.shape == (4, 13)
        np.testing.assert_allclose(seq.numpy(), want, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "order",
    [
        "Zrotation Xrotation Yrotation",
        "Yrotation Xrotation Zrotation",
        "Xrotation Yrotation Zrotation",
    ],
)
def test_motion_features_follow_the_channel_order_as_bvhio_rotates(tmp_path, order):
    """The CMU loader's features of the root, against the root rotation that bvhio itself
    builds from the same channels: heading (yaw rate), pitch and roll of R = Ry Rx Rz, and
    the displacement in the heading frame; joint angles in radians, wrapped."""
    path = _write(tmp_path / "w.bvh", _values(9), hierarchy=_hierarchy(f"{ROOT[:29]} {order}"))
    values = read_bvh(path).values
    data = load_bvh(path, downsample=2)
    assert data.features[:6] == list(ROOT_FEATURES) and data.fps == pytest.approx(60.0)
    feats = data.sequences[0].numpy()
    assert feats.shape == (4, 6 + 7)  # frames 0 2 4 6 8 -> 4 differences
    root = bvhio.readAsBvh(str(path)).Root
    kept = range(0, 9, 2)
    rot = np.array(
        [np.array(glm.mat3_cast(root.Keyframes[i].Rotation).to_list()).T for i in kept]
    )  # glm lists columns
    forward, left = rot[:, :, 2], rot[:, :, 0]
    yaw = np.arctan2(forward[:, 0], forward[:, 2])
    pitch = -np.arcsin(forward[:, 1])
    roll = np.arcsin(left[:, 1] / np.cos(pitch))
    step = np.diff(values[list(kept)][:, [0, 2]], axis=0)  # ground-plane displacement (x, z)
    tol = dict(rtol=0, atol=2e-5)  # bvhio rotates in single precision
    np.testing.assert_allclose(feats[:, 3], _wrap(np.diff(yaw)), **tol)
    np.testing.assert_allclose(feats[:, 4], pitch[1:], **tol)
    np.testing.assert_allclose(feats[:, 5], roll[1:], **tol)
    # on the ground: forward (sin yaw, cos yaw), the left (cos yaw, -sin yaw) in (x, z)
    heading = np.stack([np.sin(yaw[:-1]), np.cos(yaw[:-1])], 1)
    np.testing.assert_allclose(feats[:, 1], (step * heading).sum(1), **tol)
    np.testing.assert_allclose(feats[:, 0], (step * heading[:, ::-1] * [1, -1]).sum(1), **tol)
    np.testing.assert_allclose(feats[:, 2], values[list(kept)[1:], 1], rtol=0, atol=0)
    want = _wrap(np.deg2rad(values[list(kept)[1:], 6:]))
    np.testing.assert_allclose(feats[:, 6:], want, rtol=0, atol=1e-12)


def test_channels_asked_for_in_their_order_root_always_with_motion_features(tmp_path):
    path = _write(tmp_path / "w.bvh", _values(5))
    data = load_bvh(path, channels=["Spine.rx", "LeftLeg"], features="channels")
    assert data.features == ["Spine.rx", "LeftLeg.rx"]
    np.testing.assert_allclose(
        data.sequences[0].numpy(), _wrap(np.deg2rad(_values(5)[:, [11, 9]])), atol=1e-12
    )
    assert load_bvh(path, channels=["Hips.ry"], features="channels").features == ["root.ry"]
    data = load_bvh(path, channels=["Spine.rx"])
    assert data.features == [*ROOT_FEATURES, "Spine.rx"]


def test_labels_per_file_and_label_names(tmp_path):
    for name in ("a", "b", "c"):
        _write(tmp_path / f"{name}.bvh", _values(4, seed=len(name)))
    files = [tmp_path / "c.bvh", tmp_path / "a.bvh"]
    data = load_bvh(files, labels=["run", "walk"], label_names=["walk", "run"])
    assert data.trials == ["c", "a"] and data.labels.tolist() == [1, 0]
    assert data.label_names == ("walk", "run")
    with pytest.raises(ValueError, match=r"labels: 2 files but 1 labels"):
        load_bvh(files, labels=["run"])
    with pytest.raises(ValueError, match=r"label 'jog' of .*a\.bvh is not in label_names"):
        load_bvh(files, labels=["run", "jog"], label_names=["walk", "run"])
    with pytest.raises(TypeError, match="one label per file, not a string"):
        load_bvh(files, labels="ab")


def _refused(path: Path, match: str, **kwargs) -> None:
    with pytest.raises(ValueError, match=match):
        load_bvh(path, **kwargs)


def test_a_joint_or_channel_asked_for_but_absent_is_an_error_never_a_zero(tmp_path):
    path = _write(tmp_path / "w.bvh", _values(4))
    _refused(
        path,
        r"w\.bvh: joint 'RightUpLeg' \(asked for in channels\) is not in its "
        r"skeleton; its joints: \['Hips', 'LeftUpLeg'",
        channels=["RightUpLeg"],
    )
    _refused(
        path,
        r"w\.bvh: joint 'LeftLeg' has no channel 'rz' \(asked for in channels\); "
        r"its channels: \['rx'\]",
        channels=["LeftLeg.rz"],
        features="channels",
    )
    _refused(path, r"channels: \['Spine.rx'\] asked for twice", channels=["Spine", "Spine.rx"])
    # a second file without the joint: named, with the file
    other = _write(tmp_path / "x.bvh", _values(4), hierarchy=_hierarchy(leg="LeftShin"))
    with pytest.raises(ValueError, match=r"x\.bvh: joint 'LeftLeg' \(asked for"):
        load_bvh([path, other], channels=["LeftLeg"])


@pytest.mark.parametrize(
    ("cell", "match"),
    [
        ("nan", r"line 3[0-9] \(frame 3\): joint 'LeftLeg' rx is nan; values must be finite"),
        ("-inf", r"line 3[0-9] \(frame 3\): joint 'LeftLeg' rx is -inf; values must be finite"),
        (
            "4000",
            r"line 3[0-9] \(frame 3\): joint 'LeftLeg' rx is 4000 degrees; a joint angle beyond "
            r"\+-3600 degrees \(ten turns\) is not a physical value",
        ),
        ("1e300", r"line 3[0-9] \(frame 3\): joint 'LeftLeg' rx is 1e\+300 degrees"),
        ("abc", r"line 3[0-9] \(frame 3\): channel LeftLeg.rx is 'abc', not a number"),
    ],
)
def test_bad_values_are_refused_naming_file_line_frame_and_joint(tmp_path, cell, match):
    values = _values(5).astype(object)
    values[2, 9] = cell  # frame 3, LeftLeg.rx
    path = tmp_path / "w.bvh"
    lines = [_hierarchy(), "MOTION", "Frames: 5", "Frame Time: 0.01"]
    path.write_text("\n".join(lines + [" ".join(map(str, r)) for r in values]) + "\n")
    with pytest.raises(ValueError, match=r"BVH file .*w\.bvh: " + match):
        read_bvh(path)


def test_the_largest_angle_passes_and_positions_have_their_own_bound(tmp_path):
    values = _values(4)
    values[1, 9], values[2, 3] = MAX_ANGLE_DEGREES, -MAX_ANGLE_DEGREES
    np.testing.assert_array_equal(read_bvh(_write(tmp_path / "a.bvh", values)).values, values)
    values[3, 0] = 2e6
    with pytest.raises(
        ValueError, match=r"\(frame 4\): joint 'Hips' \(the root\) tx is 2e\+06 length units"
    ):
        read_bvh(_write(tmp_path / "b.bvh", values))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (
            dict(ft="0"),
            r"line 3[0-9]: Frame Time must be a positive number of seconds, got \['0'\]",
        ),
        (
            dict(ft="-0.01"),
            r"line 3[0-9]: Frame Time must be a positive number of seconds, got \['-0.01'\]",
        ),
        (
            dict(ft="nan"),
            r"line 3[0-9]: Frame Time must be a positive number of seconds, got \['nan'\]",
        ),
        (dict(frames=9), r"'Frames: 9' but 4 frame lines follow"),
    ],
)
def test_bad_motion_headers_are_refused(tmp_path, kwargs, match):
    _refused(_write(tmp_path / "w.bvh", _values(4), **kwargs), r"w\.bvh: " + match)


def test_a_frame_line_of_the_wrong_length_is_refused(tmp_path):
    path = _write(tmp_path / "w.bvh", _values(4))
    text = path.read_text().splitlines()
    i = text.index("Frame Time: 0.008333333") + 3  # frame 3
    text[i] = " ".join(text[i].split()[:-1])
    path.write_text("\n".join(text) + "\n")
    _refused(path, rf"line {i + 1} \(frame 3\): 12 values, but the hierarchy has 13 channels")


def test_a_truncated_file_is_refused_instead_of_hanging(tmp_path):
    """bvhio's line reader never returns at the end of a file that lacks its MOTION lines."""
    full = _write(tmp_path / "full.bvh", _values(4)).read_text()
    path = tmp_path / "cut.bvh"
    path.write_text(full[: full.index("JOINT Spine")])

    def stop(*_):
        raise TimeoutError("read_bvh did not return on a truncated file")

    old = signal.signal(signal.SIGALRM, stop)
    signal.alarm(10)
    try:
        _refused(path, r"cut\.bvh: no 'MOTION' line followed by 'Frames:' and 'Frame Time:'")
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@pytest.mark.parametrize(
    ("old", "new", "match"),
    [
        (
            "CHANNELS 1 Xrotation",
            "CHANNELS 1 Wrotation",
            r"joint 'LeftLeg' has unknown channels \['Wrotation'\]",
        ),
        (
            "CHANNELS 1 Xrotation",
            "CHANNELS 1 Xrotation Xrotation",
            r"Channel count mismatch with labels at 'CHANNELS 1 Xrotation Xrotation' \(bvhio\)",
        ),
        ("JOINT LeftLeg", "JOINT Spine", r"two joints are named 'Spine'"),
        ("JOINT LeftLeg", "JOINT root", r"a joint other than the root is named 'root'"),
        (
            "OFFSET 10.5 -5.25 0.0",
            "OFFSET 10.5 -5.25",
            r"Offset must be a 3-part tuple at 'OFFSET 10.5 -5.25' \(bvhio\)",
        ),
    ],
)
def test_malformed_hierarchies_are_refused_naming_the_file(tmp_path, old, new, match):
    values = _values(3)
    _refused(
        _write(tmp_path / "w.bvh", values, hierarchy=_hierarchy().replace(old, new, 1)),
        r"BVH file .*w\.bvh: " + match,
    )


def test_a_channel_given_twice_is_refused(tmp_path):
    hierarchy = _hierarchy().replace("CHANNELS 1 Xrotation", "CHANNELS 2 Xrotation Xrotation")
    values = np.insert(_values(3), 10, 1.0, axis=1)
    _refused(
        _write(tmp_path / "w.bvh", values, hierarchy=hierarchy),
        r"joint 'LeftLeg' gives a channel twice: \['Xrotation', 'Xrotation'\]",
    )


def test_files_of_one_call_must_share_skeleton_and_frame_rate(tmp_path):
    a = _write(tmp_path / "a.bvh", _values(4))
    b = _write(tmp_path / "b.bvh", _values(4), hierarchy=_hierarchy(leg="LeftShin"))
    with pytest.raises(
        ValueError,
        match=r"b\.bvh: its skeleton differs from that of .*a\.bvh "
        r"\(the first file\): joints only in one: \['LeftLeg'\] against "
        r"\['LeftShin'\]",
    ):
        load_bvh([a, b])
    order = _hierarchy(f"{ROOT[:29]} Yrotation Xrotation Zrotation")
    c = _write(tmp_path / "c.bvh", _values(4), hierarchy=order)
    with pytest.raises(
        ValueError,
        match=r"joint 'Hips' has channels tx ty tz rz rx ry against "
        r"tx ty tz ry rx rz",
    ):
        load_bvh([a, c])
    # bone lengths may differ (another person), the rate may be rounded otherwise
    longer = _hierarchy().replace("OFFSET 0.0 -40.0 0.0", "OFFSET 0.0 -45.0 0.0")
    d = _write(tmp_path / "d.bvh", _values(4), hierarchy=longer, ft="0.0083333")
    assert len(load_bvh([a, d])) == 2
    e = _write(tmp_path / "e.bvh", _values(4), ft="0.01")
    with pytest.raises(
        ValueError, match=r"BVH file .*e\.bvh: 100 frames/s, but .*a\.bvh has 120 frames/s"
    ):
        load_bvh([a, e])


def test_motion_features_need_the_root_positions_channels_do_not(tmp_path):
    path = _write(
        tmp_path / "w.bvh",
        _values(4, root=3),
        hierarchy=_hierarchy("Zrotation Xrotation Yrotation"),
    )
    _refused(
        path,
        r"the root joint 'Hips' has channels \['rz', 'rx', 'ry'\]; the motion "
        r"features need its three positions and three rotations",
    )
    assert load_bvh(path, features="channels").sequences[0].shape == (4, 10)
    _refused(_write(tmp_path / "one.bvh", _values(1)), r"at least 2 frames after resampling")


def test_bad_arguments_and_files(tmp_path):
    path = _write(tmp_path / "w.bvh", _values(4))
    _refused(path, r"downsample must be a positive int, got 0", downsample=0)
    _refused(path, r"unknown features 'raw'", features="raw")
    with pytest.raises(TypeError, match="channels must be a sequence of names"):
        load_bvh(path, channels="Spine")
    with pytest.raises(FileNotFoundError, match=r"BVH file not found: .*nope\.bvh"):
        load_bvh(tmp_path / "nope.bvh")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FileNotFoundError, match=r"no BVH files \(\*\.bvh\) in folder"):
        load_bvh(empty)
    with pytest.raises(ValueError, match=r"given twice"):
        load_bvh([path, tmp_path])
    (tmp_path / "blank.bvh").write_text("\n\n")
    with pytest.raises(ValueError, match=r"blank\.bvh is empty"):
        read_bvh(tmp_path / "blank.bvh")
    (tmp_path / "bin.bvh").write_bytes(b"\xff\xfe\x00\x01")
    with pytest.raises(ValueError, match=r"bin\.bvh is not a text file"):
        read_bvh(tmp_path / "bin.bvh")
