"""C3D loader on small files written here with ezc3d: trajectories read back as written, gaps
kept as gaps (and filled by the model's missing-data path), and every refusal."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hgpdm_torch.datasets import MotionTrials, Standardizer, load_c3d, read_c3d

ezc3d = pytest.importorskip("ezc3d", reason="the C3D loader needs ezc3d (the data extra)")


def _markers(frames: int, phase: float = 0.0) -> np.ndarray:
    """``[frames, 2, 3]``: two markers (mm) circling as in a periodic movement."""
    w = 2 * np.pi * np.arange(frames) / 20 + phase
    a = np.stack([100 * np.cos(w), 50 * np.sin(w), 1000 + 0 * w], 1)
    b = np.stack([200 + 30 * np.sin(w), 80 * np.cos(w), 900 + 10 * np.sin(2 * w)], 1)
    return np.stack([a, b], 1)


def _write(
    path: Path,
    positions: np.ndarray,
    labels: tuple[str, ...] = ("LASI", "RASI"),
    *,
    rate: float = 100.0,
    residuals: np.ndarray | None = None,
    units: str | None = "mm",
    first_frame: int = 0,
) -> Path:
    """A C3D file of ``positions [T, M, 3]``; ``residuals [T, M]`` (negative: a gap)."""
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = labels
    if units is not None:
        c3d.add_parameter("POINT", "UNITS", [units])
    points = np.ones((4, positions.shape[1], positions.shape[0]))
    points[:3] = positions.transpose(2, 1, 0)
    c3d["data"]["points"] = points
    if residuals is not None:
        c3d["data"]["meta_points"]["residuals"] = residuals.T[None].astype(float)
    c3d["header"]["points"]["first_frame"] = first_frame
    c3d.write(str(path))
    return path


def _single(x: np.ndarray) -> np.ndarray:
    """What a float C3D file stores: single precision."""
    return x.astype(np.float32).astype(np.float64)


def test_trajectories_read_back_as_written_named_at_the_file_rate(tmp_path):
    pos = _markers(12)
    _write(tmp_path / "a.c3d", pos)
    _write(tmp_path / "b.c3d", _markers(9, 1.0))
    data = read_c3d(tmp_path / "a.c3d")
    np.testing.assert_array_equal(data.positions, _single(pos))
    assert data.labels == ["LASI", "RASI"] and data.fps == 100.0 and data.units == "mm"
    assert data.first_frame == 1
    trials = load_c3d(tmp_path, downsample=4)
    assert isinstance(trials, MotionTrials)
    assert trials.trials == ["a", "b"] and trials.label_names == (tmp_path.name,)
    assert trials.features == ["LASI.x", "LASI.y", "LASI.z", "RASI.x", "RASI.y", "RASI.z"]
    assert trials.fps == 25.0 and trials.units == "mm" and trials.missing == []
    assert trials.missing_frames == {"a": {"LASI": 0, "RASI": 0}, "b": {"LASI": 0, "RASI": 0}}
    seq = trials.sequences[0]
    assert seq.dtype == torch.float64 and seq.shape == (3, 6)  # frames 0 4 8
    np.testing.assert_array_equal(seq.numpy(), _single(pos)[::4].reshape(3, 6))
    assert trials.sequences[1].shape == (3, 6)  # 9 frames: 0 4 8


def test_markers_asked_for_in_their_order_labels_per_file(tmp_path):
    pos = _markers(5)
    a = _write(tmp_path / "a.c3d", pos)
    b = _write(tmp_path / "b.c3d", pos[:, ::-1], labels=("RASI", "LASI"))
    trials = load_c3d([b, a], ["RASI"], labels=["walk", "run"])
    assert trials.features == ["RASI.x", "RASI.y", "RASI.z"]
    assert trials.label_names == ("walk", "run") and trials.labels.tolist() == [0, 1]
    for seq in trials.sequences:  # RASI found by its label in both files
        np.testing.assert_array_equal(seq.numpy(), _single(pos[:, 1]))
    # all markers of the first file, in its order, found by label in the others
    both = load_c3d([a, b])
    np.testing.assert_array_equal(both.sequences[0].numpy(), both.sequences[1].numpy())


def test_a_gap_is_missing_never_zero_or_interpolated_and_counted(tmp_path):
    pos = _markers(10)
    residuals = np.zeros((10, 2))
    residuals[3:6, 0] = -1  # LASI occluded in frames 4-6
    pos[8, 1] = np.nan  # RASI not reconstructed in frame 9 (NaN in the file)
    pos[1, 1] = 0.0  # RASI zero-filled in frame 2 by an older writer
    path = _write(tmp_path / "g.c3d", pos, residuals=residuals)
    rows = load_c3d(path)
    assert rows.missing_frames == {"g": {"LASI": 3, "RASI": 2}}
    gone = [1, 3, 4, 5, 8]
    seq = rows.sequences[0].numpy()
    assert np.isnan(seq[gone]).all()
    kept = [i for i in range(10) if i not in gone]
    np.testing.assert_array_equal(seq[kept], _single(pos[kept]).reshape(-1, 6))
    # only the occluded marker's columns, on request
    cols = load_c3d(path, gaps="markers").sequences[0].numpy()
    assert np.isnan(cols[3:6, :3]).all() and np.isfinite(cols[3:6, 3:]).all()
    np.testing.assert_array_equal(cols[3:6, 3:], _single(pos[3:6, 1]))
    assert np.isnan(cols[[1, 8], 3:]).all() and np.isfinite(cols[[1, 8], :3]).all()
    # down-sampling keeps a missing row missing
    assert np.isnan(load_c3d(path, downsample=4).sequences[0].numpy()[1]).all()  # frame 4
    with pytest.raises(
        ValueError,
        match=r"g\.c3d: marker 'LASI' is missing in frames 4-6 \(3 frames\); pass "
        r"gaps='frames' to read them as missing \(NaN\) frames",
    ):
        load_c3d(path, gaps="error")
    with pytest.raises(ValueError, match=r"marker 'RASI' is missing in frames 2, 9 \(2 frames\)"):
        load_c3d(path, ["RASI"], gaps="error")


def test_the_models_missing_data_path_fills_a_c3d_gap(tmp_path):
    """A loaded C3D gap (4 frames of one marker occluded) is what the inference takes as
    missing: VB on a GPDM fitted to a complete recording recovers it from the frames around,
    close to the marker's true path."""
    from hgpdm_torch.inference.variational import VariationalInference
    from hgpdm_torch.models import GPDM

    train = load_c3d(_write(tmp_path / "train.c3d", _markers(40)))
    truth = _markers(20, 0.3)
    residuals = np.zeros((20, 2))
    residuals[8:12, 0] = -1
    test = load_c3d(_write(tmp_path / "test.c3d", truth, residuals=residuals))
    gap = test.sequences[0]
    assert torch.isnan(gap[8:12]).all() and not torch.isnan(gap[:8]).any()
    std = Standardizer().fit(train.sequences)
    torch.manual_seed(0)
    model = GPDM([std.transform(s) for s in train.sequences], 2)
    model.fit(40, warn=False)
    vb = VariationalInference(model)
    window = std.transform(gap)[None]  # the gap stays missing
    rec, var = vb.predict_observations(window, vb.infer(window))
    filled = std.inverse_transform(rec[0])[8:12].numpy()
    assert np.isfinite(filled).all() and (var[0, 8:12] > 0).all()
    true = _single(truth[8:12]).reshape(4, 6)
    # within 3 mm on paths of radius 30 to 100 mm (a straight line across the gap: 28 mm off)
    np.testing.assert_allclose(filled, true, rtol=0, atol=3.0)


def test_a_marker_asked_for_but_absent_is_an_error(tmp_path):
    path = _write(tmp_path / "a.c3d", _markers(5))
    with pytest.raises(
        ValueError,
        match=r"a\.c3d: marker 'LKNE' is not in the file; its markers: \['LASI', 'RASI'\]",
    ):
        load_c3d(path, ["LASI", "LKNE"])
    other = _write(tmp_path / "b.c3d", _markers(5), labels=("LASI", "LKNE"))
    with pytest.raises(
        ValueError,
        match=r"b\.c3d: its markers differ from those of .*a\.c3d \(the first file\): only "
        r"here \['LKNE'\], only there \['RASI'\]",
    ):
        load_c3d([path, other])
    with pytest.raises(ValueError, match=r"b\.c3d: marker 'RASI' is not in the file"):
        load_c3d([path, other], ["RASI"])
    twice = _write(tmp_path / "c.c3d", _markers(5), labels=("LASI", "LASI"))
    with pytest.raises(ValueError, match=r"c\.c3d: markers \['LASI'\] are labelled twice"):
        load_c3d(twice)
    with pytest.raises(ValueError, match=r"c\.c3d: marker 'LASI' is labelled 2 times"):
        load_c3d(twice, ["LASI"])
    with pytest.raises(TypeError, match="markers must be a sequence of marker labels"):
        load_c3d(path, "LASI")


def test_a_marker_never_seen_is_refused(tmp_path):
    residuals = np.zeros((6, 2))
    residuals[:, 1] = -1
    path = _write(tmp_path / "a.c3d", _markers(6), residuals=residuals)
    with pytest.raises(ValueError, match=r"markers \['RASI'\] are missing in all 6 frames"):
        load_c3d(path)
    assert load_c3d(path, ["LASI"]).missing_frames == {"a": {"LASI": 0}}


@pytest.mark.parametrize(
    ("value", "match"),
    [
        (np.inf, r"frame 13: marker 'RASI' y is inf; coordinates must be finite"),
        (-2e6, r"frame 13: marker 'RASI' y is -2e\+06 length units; a position beyond "),
    ],
)
def test_bad_coordinates_are_refused_naming_frame_and_marker(tmp_path, value, match):
    pos = _markers(6)
    pos[2, 1, 1] = value
    path = _write(tmp_path / "a.c3d", pos, first_frame=10)  # frames 11-16
    with pytest.raises(ValueError, match=r"C3D file .*a\.c3d: " + match):
        load_c3d(path)


def test_files_of_one_call_must_share_rate_and_units(tmp_path):
    a = _write(tmp_path / "a.c3d", _markers(5))
    b = _write(tmp_path / "b.c3d", _markers(5), rate=120.0)
    with pytest.raises(ValueError, match=r"b\.c3d: 120 frames/s, but .*a\.c3d has 100 frames/s"):
        load_c3d([a, b])
    c = _write(tmp_path / "c.c3d", _markers(5), units="m")
    with pytest.raises(ValueError, match=r"c\.c3d: units 'm', but .*a\.c3d has 'mm'"):
        load_c3d([a, c])


def _patch_float(path: Path, old: float, new: float, *, after: int | None = None) -> None:
    """Replace the single-precision ``old`` by ``new``: everywhere, or only its first
    occurrence from byte ``after`` on."""
    raw = path.read_bytes()
    want, put = np.float32(old).tobytes(), np.float32(new).tobytes()
    if after is None:
        path.write_bytes(raw.replace(want, put))
        return
    at = raw.index(want, after)
    path.write_bytes(raw[:at] + put + raw[at + 4 :])


@pytest.mark.parametrize("rate", [0.0, -100.0, np.nan])
def test_a_frame_rate_that_is_not_positive_is_refused(tmp_path, rate):
    """ezc3d cannot write such a file: the rate is patched in (header and POINT:RATE)."""
    path = _write(tmp_path / "a.c3d", _markers(5), rate=100.0)
    _patch_float(path, 100.0, rate)
    with pytest.raises(ValueError, match=r"a\.c3d: frame rate \(header\) must be a positive"):
        load_c3d(path)


def test_a_point_rate_that_is_not_positive_is_refused(tmp_path):
    """POINT:RATE alone patched: the first rate in the parameters, which start at byte 512
    (ezc3d itself takes the header's rate for a zero, and fails on a NaN)."""
    path = _write(tmp_path / "b.c3d", _markers(5), rate=100.0)
    _patch_float(path, 100.0, -100.0, after=512)
    with pytest.raises(ValueError, match=r"b\.c3d: frame rate \(POINT:RATE\) must be a positive"):
        load_c3d(path)


def test_a_header_rate_that_disagrees_with_point_rate_is_refused(tmp_path):
    path = _write(tmp_path / "a.c3d", _markers(5), rate=100.0)
    _patch_float(path, 100.0, 120.0, after=512)
    with pytest.raises(
        ValueError, match=r"the header's frame rate 100 and POINT:RATE 120 disagree"
    ):
        load_c3d(path)


def test_truncated_and_foreign_files_are_refused_before_ezc3d_reads_them(tmp_path):
    """ezc3d crashes the interpreter, never returns or reads garbage on a file cut short in its
    parameters (run in a child process: a crash or hang there fails this test instead of ending
    the run), and reads a file cut short in its frames as a shorter one."""
    full = _write(tmp_path / "full.c3d", _markers(5)).read_bytes()
    cuts = {
        300: r"is not a C3D file \(no C3D header\)",
        520: r"its frames should start at byte 1536, but the file has 520 bytes",
        700: r"its frames should start at byte 1536, but the file has 700 bytes",
        1600: r"its header announces 5 frames, which need 1696 bytes, but the file has 1600 "
        r"bytes \(2 frames read; truncated\?\)",
    }
    for size in cuts:
        (tmp_path / f"cut{size}.c3d").write_bytes(full[:size])
    script = (
        "import sys\nfrom hgpdm_torch.datasets.c3d import read_c3d\n"
        "for path in sys.argv[1:]:\n"
        "    try:\n        read_c3d(path)\n"
        "    except ValueError as err:\n        print(err)\n"
        "    else:\n        print('read', path)\n"
    )
    paths = [str(tmp_path / f"cut{size}.c3d") for size in cuts]
    out = subprocess.run(
        [sys.executable, "-c", script, *paths],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(__file__).resolve().parents[2],
    )
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert len(lines) == len(cuts), out.stdout
    for line, (size, match) in zip(lines, cuts.items(), strict=True):
        assert re.search(rf"C3D file .*cut{size}\.c3d:? " + match, line), line
    text = tmp_path / "text.c3d"
    text.write_text("x" * 600)
    with pytest.raises(ValueError, match=r"text\.c3d is not a C3D file"):
        load_c3d(text)


def test_bad_arguments_and_files(tmp_path):
    path = _write(tmp_path / "a.c3d", _markers(5))
    with pytest.raises(ValueError, match=r"unknown gaps 'zero'"):
        load_c3d(path, gaps="zero")
    with pytest.raises(ValueError, match=r"downsample must be a positive int, got 1.5"):
        load_c3d(path, downsample=1.5)
    with pytest.raises(FileNotFoundError, match=r"C3D file not found: .*b\.c3d"):
        load_c3d([path, tmp_path / "b.c3d"])
    with pytest.raises(FileNotFoundError, match=r"no C3D files \(\*\.c3d\) in folder"):
        load_c3d(tmp_path / "nothing" if (tmp_path / "nothing").mkdir() is None else tmp_path)
    with pytest.raises(ValueError, match=r"labels: 1 files but 2 labels"):
        load_c3d(path, labels=["a", "b"])
