"""The CMU protocols and the trial loader: CRLF and LF files, each subject's skeleton, missing
trials reported, the thesis's trial lists, and the real files when ../shared/data/cmu is there."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from hgpdm_torch.datasets.cmu import PROTOCOLS, Protocol, load_protocol, load_trials
from hgpdm_torch.datasets.mocap import read_amc, read_asf
from hgpdm_torch.datasets.walkers import motion_features

from .test_mocap import ASF, _amc

CMU = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "cmu"


def _write(folder: Path, name: str, text: str, crlf: bool = False) -> None:
    (folder / name).write_bytes(text.replace("\n", "\r\n" if crlf else "\n").encode())


@pytest.fixture
def cmu(tmp_path):
    """Subject 01 (LF files) and 02 (CRLF files, a longer femur in its own skeleton)."""
    _write(tmp_path, "01.asf", ASF)
    _write(tmp_path, "02.asf", ASF.replace("length 7.15815", "length 9.5"), crlf=True)
    _write(tmp_path, "01_01.amc", _amc(41))
    _write(tmp_path, "01_02.amc", _amc(31))
    _write(tmp_path, "02_01.amc", _amc(41), crlf=True)
    return tmp_path


def test_trials_read_with_their_own_skeleton_crlf_like_lf_and_missing_reported(cmu):
    trials = [("01_01", "a"), ("02_01", "b"), ("02_07", "b"), ("01_02", "a")]
    data = load_trials(trials, cmu, downsample=10)
    assert data.trials == ["01_01", "02_01", "01_02"] and data.missing == ["02_07"]
    assert data.labels.tolist() == [0, 1, 0] and data.label_names == ("a", "b")
    assert data.fps == 12.0
    # 41 frames at stride 10 -> 5 resampled -> 4 rows (backward differences)
    assert [s.shape[0] for s in data.sequences] == [4, 4, 3]
    # the CRLF trial of subject 02 equals its LF twin, read through its own skeleton
    sk = read_asf(cmu / "02.asf")
    assert sk.bones["lfemur"].length == 9.5
    amc = read_amc(cmu / "02_01.amc", sk)
    want, names = motion_features(amc.values, amc.channels, sk, 120.0, 12.0)
    torch.testing.assert_close(data.sequences[1], torch.as_tensor(want), rtol=0, atol=0)
    torch.testing.assert_close(data.sequences[1], data.sequences[0], rtol=0, atol=0)
    assert data.features == names
    with pytest.raises(FileNotFoundError, match=re.escape("02_07.amc")):
        load_trials(trials, cmu, downsample=10, require_all=True)


def test_a_test_folder_may_use_the_training_folders_skeletons(cmu, tmp_path_factory):
    other = tmp_path_factory.mktemp("test_trials")
    _write(other, "01_09.amc", _amc(21))
    data = load_trials([("01_09", "a")], [other, cmu], downsample=4)
    assert data.trials == ["01_09"] and data.sequences[0].shape[0] == 5 and data.fps == 30.0
    missing = load_trials([("01_09", "a")], [other], downsample=4)  # no 01.asf there
    assert missing.trials == [] and missing.missing == ["01_09"]


def test_bad_arguments(cmu):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_trials([("01_01", "a")], cmu / "nowhere", downsample=10)
    with pytest.raises(ValueError, match="downsample"):
        load_trials([("01_01", "a")], cmu, downsample=0)
    with pytest.raises(ValueError, match="CMU names"):
        load_trials([("01-01", "a")], cmu, downsample=10)
    with pytest.raises(ValueError, match="label 'c'"):
        load_trials([("01_01", "c")], cmu, downsample=10, label_names=("a", "b"))
    with pytest.raises(ValueError, match="protocol"):
        load_protocol("dancers", folder=cmu)
    with pytest.raises(ValueError, match="split"):
        PROTOCOLS["walkers"].trials("validation")


def test_protocols_are_the_thesis_trial_lists():
    """Sec. 2.4.1's training and test trials, labels and down-sampling, written out again."""
    walkers = PROTOCOLS["walkers"]
    assert [t for t, _ in walkers.train] == [
        "07_01", "07_02", "07_03", "08_01", "08_02", "08_03", "16_15", "16_16",
        "35_01", "35_02", "35_03",
    ]  # fmt: skip
    want_test = [f"07_{k:02d}" for k in range(6, 11)] + ["08_08", "08_09", "16_22"]
    assert [t for t, _ in walkers.test] == want_test + [f"35_{k:02d}" for k in range(4, 11)]
    assert all(t.split("_")[0] == s for t, s in walkers.train + walkers.test)
    assert walkers.downsample == 10 and walkers.fps == 12.0
    weird = PROTOCOLS["weird-walking"]
    numbers = {s: [int(t[4:]) for t, lab in weird.train if lab == s] for s in weird.label_names}
    assert numbers == {
        "arms out": [1, 2, 3, 4, 5],
        "fast": [17, 18, 19],
        "hopping on the left foot": [23, 24, 25],
        "slow": [45, 46, 47],
    }
    assert sorted(int(t[4:]) for t, _ in weird.test) == [
        *range(6, 13), 20, 21, 22, 26, 27, 28, 48, 49, 50,
    ]  # fmt: skip
    four = PROTOCOLS["four-walkers"]
    assert [t for t, _ in four.train] == ["35_02", "10_04", "12_01", "16_05"]
    assert [t for t, _ in four.test] == ["35_03", "12_02", "12_03", "16_21"]
    assert four.downsample == 4 and four.fps == 30.0
    for p in PROTOCOLS.values():
        assert isinstance(p, Protocol) and p.name in PROTOCOLS
        assert not {t for t, _ in p.train} & {t for t, _ in p.test}
        assert {lab for _, lab in p.train + p.test} <= set(p.label_names)


def test_protocol_round_trip_through_load_trials(cmu):
    """A user-defined protocol loads like a named one."""
    mine = Protocol("mine", "subject", ("01", "02"), (("01_01", "01"), ("02_01", "02")),
                    (("01_02", "01"),), 10, "none")  # fmt: skip
    train, test = load_protocol(mine, "train", cmu), load_protocol(mine, "test", cmu)
    assert train.trials == ["01_01", "02_01"] and train.labels.tolist() == [0, 1]
    assert test.trials == ["01_02"] and test.labels.tolist() == [0] and not test.missing


@pytest.mark.skipif(not CMU.is_dir(), reason=f"../shared/data/cmu absent: no CMU files at {CMU}")
def test_real_protocols_load_and_report_what_is_absent():
    walkers = load_protocol("walkers", folder=CMU)
    assert walkers.trials == ["07_01", "07_02", "08_02", "16_15", "16_16", "35_01", "35_02",
                              "35_03"]  # fmt: skip
    assert walkers.missing == ["07_03", "08_01", "08_03"]
    assert walkers.labels.tolist() == [0, 0, 1, 2, 2, 3, 3, 3] and walkers.fps == 12.0
    # 07_01: 316 frames at 120 frames/s -> 32 at 12 -> 31 rows
    assert walkers.sequences[0].shape == (31, 62) and len(walkers.features) == 62
    weird = load_protocol("weird-walking", folder=CMU)  # CRLF files
    assert len(weird) == 14 and not weird.missing
    assert weird.labels.bincount().tolist() == [5, 3, 3, 3]
    # 132_01: 1413 frames -> 142 -> 141 rows
    assert weird.sequences[0].shape[0] == 141
    assert all(bool(torch.isfinite(s).all()) for s in walkers.sequences + weird.sequences)
    four = load_protocol("four-walkers", folder=CMU)
    assert four.trials == ["35_02", "16_05"] and four.missing == ["10_04", "12_01"]
    assert four.fps == 30.0
    test = load_protocol("four-walkers", "test", CMU)
    assert test.trials == ["35_03"] and test.missing == ["12_02", "12_03", "16_21"]


@pytest.mark.skipif(not CMU.is_dir(), reason=f"../shared/data/cmu absent: no CMU files at {CMU}")
def test_real_walkers_advance_at_a_plausible_speed():
    """Every Walkers subject advances along its heading at 0.9-1.7 m/s, not sideways; the
    pelvis is 0.8-1.1 m high."""
    data = load_protocol("walkers", folder=CMU)
    unit = 0.0254 / 0.45  # CMU ASF "length 0.45": inches / 0.45
    fwd, side = data.features.index("root.vz_heading"), data.features.index("root.vx_heading")
    for code in range(4):
        v = torch.cat([s for s, g in zip(data.sequences, data.labels, strict=True) if g == code])
        speed = float(v[:, fwd].mean()) * data.fps * unit
        assert 0.9 < speed < 1.7, (data.label_names[code], speed)
        # sideways at most a fifth of forward (08's one trial, 08_02, drifts left by 13%)
        assert abs(float(v[:, side].mean())) < 0.2 * float(v[:, fwd].mean())
    height = torch.cat(data.sequences)[:, data.features.index("root.ty")] * unit
    assert 0.8 < float(height.mean()) < 1.1


# ------------------------------------------------------------------------------------------
# Files with missing bones or frames (issue 54)
# ------------------------------------------------------------------------------------------


def _without(text: str, frames: set[int], prefix: str = "") -> str:
    """``text`` (an AMC file) without the lines starting with ``prefix`` in ``frames`` (with
    ``prefix=""``: without those frames at all, numbers included)."""
    out, frame = [], 0
    for line in text.splitlines():
        if line.isdigit():
            frame = int(line)
        if not (frame in frames and line.startswith(prefix)):
            out.append(line)
    return "\n".join(out) + "\n"


def test_a_trial_without_a_bone_is_refused_naming_file_frame_and_bone(cmu):
    _write(cmu, "01_03.amc", _without(_amc(41), {17}, "lfemur "))
    with pytest.raises(ValueError, match=r"01_03\.amc: frame 17 lacks bones \['lfemur'\]"):
        load_trials([("01_03", "a")], cmu, downsample=10)
    _write(cmu, "01_03.amc", _without(_amc(41), set(range(1, 42)), "lfemur "))
    with pytest.raises(ValueError, match=r"01_03\.amc: bones \['lfemur'\] .* no line in any frame"):
        load_trials([("01_03", "a")], cmu, downsample=10)


def test_missing_frames_are_refused_or_become_missing_rows(cmu):
    # 01_01 without frame 21: at stride 10 the resampled frames are 1, 11, 21, 31, 41, so
    # feature rows 1 (frame 11 -> 21) and 2 (21 -> 31) lack it
    _write(cmu, "01_04.amc", _without(_amc(41), {21}))
    trials = [("01_01", "a"), ("01_04", "a")]
    with pytest.raises(ValueError, match=r"01_04\.amc: line \d+: frame 22 follows frame 20, so "
                       r"frame 21 is missing; pass gaps='missing'"):  # fmt: skip
        load_trials(trials, cmu, downsample=10)
    with pytest.raises(ValueError, match=r"01_04\.amc: .*frame 21 is missing"):
        load_protocol(Protocol("p", "subject", ("a",), tuple(trials), (), 10, "none"), "train", cmu)
    data = load_trials(trials, cmu, downsample=10, gaps="missing")
    full, gappy = data.sequences
    assert gappy.shape == full.shape == (4, len(data.features))
    assert torch.isnan(gappy[1:3]).all() and not torch.isnan(gappy[[0, 3]]).any()
    torch.testing.assert_close(gappy[[0, 3]], full[[0, 3]], rtol=0, atol=0)
    # a missing frame between the resampled ones changes nothing
    _write(cmu, "01_04.amc", _without(_amc(41), {25, 26}))
    gappy = load_trials([("01_04", "a")], cmu, downsample=10, gaps="missing").sequences[0]
    torch.testing.assert_close(gappy, full, rtol=0, atol=0)
    with pytest.raises(ValueError, match="gaps"):
        load_trials(trials, cmu, downsample=10, gaps="skip")
