"""C3D motion-capture files (marker trajectories) as :class:`~.cmu.MotionTrials`.

C3D is the binary format of optical marker systems (Vicon Nexus, Qualisys, OptiTrack, Motion
Analysis): every frame gives each labelled marker's ``x y z`` position and a residual, which is
negative when the marker was not reconstructed in that frame (occluded: a gap).

Why this reader: ``ezc3d`` (maintained, on PyPI: 1.7 released in 2026) reads every C3D variant
(Intel, DEC and MIPS processors, integer and float storage with ``POINT:SCALE``,
``POINT:LABELS2``... for more than 255 markers) and marks a point whose residual is negative as
NaN. A point exactly at ``(0, 0, 0)`` is missing too: some writers fill gaps with zeros rather
than flag them, and no real marker sits exactly at the origin in all three coordinates.

A gap stays a gap: a frame in which a marker is missing is a missing observation (rows of NaN,
the toolkit's inference takes them, e.g. gap recovery fills them), or an error with
``gaps="error"``; nothing is zero-filled or interpolated. :attr:`MarkerTrials.missing_frames`
says how many frames each marker misses in each file.

Refused, naming the file (and the marker, and frame where there is one): a marker asked for that
the file lacks or labels twice, a marker never seen in any frame, an infinite coordinate or one
beyond +-:data:`~.mocap.MAX_LENGTH`, a frame rate that is not a positive finite number (or a
header and ``POINT:RATE`` that disagree), files of one call with other markers (with
``markers=None``), frame rates or units, and ``gaps="error"`` on a file with gaps.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..validation import check_choice
from .bvh import check_downsample, check_rate, recording_files, recording_labels, trial_names
from .cmu import MotionTrials
from .mocap import MAX_LENGTH

__all__ = ["C3D_GAPS", "C3dMarkers", "MarkerTrials", "load_c3d", "read_c3d"]

#: what :func:`load_c3d` does with a frame in which a marker is missing
C3D_GAPS = ("frames", "markers", "error")


@dataclass
class MarkerTrials(MotionTrials):
    """:class:`~.cmu.MotionTrials` of marker trajectories, with what was missing.

    Attributes:
        missing_frames: per trial name, each chosen marker's number of missing frames in the
            file (at its own frame rate, before down-sampling).
        units: the files' ``POINT:UNITS`` (e.g. ``"mm"``; ``""`` where the files state none).
    """

    missing_frames: dict[str, dict[str, int]] = field(default_factory=dict)
    units: str = ""


@dataclass
class C3dMarkers:
    """A C3D file's markers as written.

    Attributes:
        positions: ``[T, M, 3]`` (float64) ``x y z`` of every marker in every frame; NaN where
            the marker is missing (a negative residual, NaN in the file, or a point exactly at
            ``(0, 0, 0)``, which some writers put in a gap).
        labels: the ``M`` marker labels (``POINT:LABELS``, ``LABELS2``, ...).
        fps: the frame rate (``POINT:RATE``).
        first_frame: the number of the first frame (1 unless the file says otherwise).
        units: ``POINT:UNITS`` (``""`` if none).
    """

    positions: np.ndarray
    labels: list[str]
    fps: float
    first_frame: int
    units: str


def _parameter(group: dict, name: str) -> list:
    entry = group.get(name)
    if entry is None:
        return []
    value = entry["value"]
    return list(np.asarray(value).ravel()) if isinstance(value, np.ndarray) else list(value)


def read_c3d(path: str | Path) -> C3dMarkers:
    """Read a C3D file's marker trajectories through ``ezc3d``.

    Returns:
        :class:`C3dMarkers`: positions ``[T, M, 3]`` (NaN where missing), labels, frame rate,
        first frame number, units.

    Raises:
        FileNotFoundError: no such file.
        ImportError: ``ezc3d`` is not installed.
        ValueError: naming the file: not a C3D file, no markers or frames, labels that do not
            match the markers, a frame rate that is not a positive finite number or that differs
            between the header and ``POINT:RATE``, an infinite coordinate or one beyond
            +-:data:`~.mocap.MAX_LENGTH` (naming marker and frame).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"C3D file not found: {path}")
    try:
        import ezc3d
    except ImportError as err:  # optional extra
        raise ImportError(
            "reading C3D files needs the ezc3d package: pip install 'hgpdm-torch[data]'"
        ) from err
    header = _header(path)
    try:
        c3d = ezc3d.c3d(str(path))
    except (RuntimeError, ValueError, OSError) as err:
        raise ValueError(f"C3D file {path}: ezc3d cannot read it ({err})") from None
    point = c3d["parameters"]["POINT"]
    labels, k = [str(s).strip() for s in _parameter(point, "LABELS")], 2
    while f"LABELS{k}" in point:
        labels += [str(s).strip() for s in _parameter(point, f"LABELS{k}")]
        k += 1
    points = np.asarray(c3d["data"]["points"], dtype=float)  # [4, M, T]
    if points.ndim != 3 or points.shape[1] == 0 or points.shape[2] == 0:
        raise ValueError(f"C3D file {path} holds no marker frames (points of shape {points.shape})")
    if len(labels) < points.shape[1]:
        raise ValueError(
            f"C3D file {path}: {points.shape[1]} markers but {len(labels)} labels in POINT:LABELS"
        )
    labels = labels[: points.shape[1]]  # POINT:LABELS may list unused ones beyond POINT:USED
    _check_frames(path, c3d, header)
    fps = _rate(path, header.rate, _parameter(point, "RATE"))
    positions = points[:3].transpose(2, 1, 0).copy()  # [T, M, 3]
    residuals = np.asarray(c3d["data"]["meta_points"]["residuals"], dtype=float)
    if residuals.shape == (1, *points.shape[1:]):  # ezc3d already gives NaN for these
        positions[residuals[0].T < 0] = np.nan
    # some writers fill a gap with zeros instead of flagging it; no marker sits exactly there
    positions[(positions == 0).all(-1)] = np.nan
    first = int(c3d["header"]["points"]["first_frame"]) + 1  # ezc3d counts from 0
    units = "".join(str(s).strip() for s in _parameter(point, "UNITS"))
    _check_positions(path, positions, labels, first)
    return C3dMarkers(positions, labels, fps, first, units)


class _Layout(NamedTuple):
    """What a C3D header says: the byte where the frames start, the number of frames (``None``
    past the header's 16-bit range), the analog samples per frame, the frame rate."""

    start: int
    frames: int | None
    analogs: int
    rate: float


def _header(path: Path) -> _Layout:
    """What a C3D file's header says (:class:`_Layout`), refusing a file that ends before its
    frames or whose frame rate is not a positive number.

    Read before ``ezc3d`` reads the file: on a file cut short in its header or parameters it
    crashes the interpreter, never returns, or reads garbage as frames, and it counts the frames
    of a file cut short in its frames as if there were no more. The header's first byte is the
    parameter block's number, its second 80; the parameter block's fourth byte is the processor
    (84 Intel, 85 DEC, 86 MIPS: big-endian), whose byte order the header's words are in: 3 the
    analog samples per frame, 4 and 5 the first and last frame, 9 the first data block (from 1),
    11-12 the frame rate (a float; DEC's has its two words swapped and reads 4 times larger).
    ``ezc3d`` fails on a NaN rate with an out-of-memory message, so it is checked here too.
    """
    size = path.stat().st_size
    with path.open("rb") as f:
        header = f.read(512)
        if len(header) < 512 or header[1] != 80 or header[0] < 2:
            raise ValueError(f"C3D file {path} is not a C3D file (no C3D header)")
        f.seek((header[0] - 1) * 512)
        parameters = f.read(4)
    if len(parameters) < 4 or parameters[3] not in (84, 85, 86):
        raise ValueError(
            f"C3D file {path}: its parameter section is missing or has no processor type "
            "(truncated, or not a C3D file)"
        )
    order = "big" if parameters[3] == 86 else "little"
    analogs, first, last, _, _, _, block = (
        int.from_bytes(header[i : i + 2], order) for i in range(4, 18, 2)
    )
    start = (block - 1) * 512
    if block <= header[0] or size < start:
        raise ValueError(
            f"C3D file {path}: its frames should start at byte {start}, but the file has "
            f"{size} bytes (truncated?)"
        )
    raw = header[20:24]
    if parameters[3] == 85:
        rate = struct.unpack("<f", raw[2:] + raw[:2])[0] / 4
    else:
        rate = struct.unpack(">f" if order == "big" else "<f", raw)[0]
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(
            f"C3D file {path}: frame rate (header) must be a positive number of frames per "
            f"second, got {rate:g}"
        )
    announced = last - first + 1 if first <= last < 65535 else None
    return _Layout(start, announced, analogs, rate)


def _check_frames(path: Path, c3d, header: _Layout) -> None:
    """Refuse a file cut short in its frames: fewer frames read than the header announces, or
    fewer bytes than its frames take (per frame 4 words a marker and a word per analog sample;
    a word is 4 bytes in float storage, ``POINT:SCALE < 0``, else 2)."""
    start, announced, analogs, _ = header
    markers, frames = c3d["data"]["points"].shape[1:]
    scale = _parameter(c3d["parameters"]["POINT"], "SCALE")
    word = 4 if scale and float(scale[0]) < 0 else 2
    expected = frames if announced is None else announced
    needed = start + word * expected * (4 * markers + analogs)
    size = path.stat().st_size
    if frames < expected or size < needed:
        raise ValueError(
            f"C3D file {path}: its header announces {expected} frames, which need {needed} "
            f"bytes, but the file has {size} bytes ({frames} frames read; truncated?)"
        )


def _rate(path: Path, header: float, parameter: list) -> float:
    """The frame rate from ``POINT:RATE`` (else the header's), positive and finite, and the two
    the same where both are given (``ezc3d`` overwrites the header's with ``POINT:RATE``: the
    header's is read by :func:`_header`)."""
    rate = float(parameter[0]) if parameter else header
    if not (math.isfinite(rate) and rate > 0):
        raise ValueError(
            f"C3D file {path}: frame rate (POINT:RATE) must be a positive number of frames per "
            f"second, got {rate:g}"
        )
    if abs(header - rate) > 1e-4 * rate:
        raise ValueError(
            f"C3D file {path}: the header's frame rate {header:g} and POINT:RATE {rate:g} "
            "disagree; which one is right cannot be told"
        )
    return rate


def _check_positions(path: Path, positions: np.ndarray, labels: list[str], first: int) -> None:
    """Refuse infinite coordinates and coordinates beyond :data:`MAX_LENGTH` (NaN: missing)."""
    with np.errstate(invalid="ignore"):
        bad = np.isinf(positions) | (np.abs(positions) > MAX_LENGTH)
    if not bad.any():
        return
    frame, marker, axis = np.argwhere(bad)[0]
    value = positions[frame, marker, axis]
    where = f"C3D file {path}: frame {first + frame}: marker {labels[marker]!r} {'xyz'[axis]}"
    if np.isinf(value):
        raise ValueError(f"{where} is {value}; coordinates must be finite (NaN marks a gap)")
    raise ValueError(
        f"{where} is {value:g} length units; a position beyond +-{MAX_LENGTH:g} is not a "
        "physical value"
    )


def _choose(path: Path, data: C3dMarkers, markers: Sequence[str]) -> list[int]:
    """The index of each marker asked for, refusing absent and twice-labelled ones."""
    out = []
    for name in markers:
        hits = [i for i, label in enumerate(data.labels) if label == name]
        if not hits:
            raise ValueError(
                f"C3D file {path}: marker {name!r} is not in the file; its markers: {data.labels}"
            )
        if len(hits) > 1:
            raise ValueError(
                f"C3D file {path}: marker {name!r} is labelled {len(hits)} times; which one is "
                "meant cannot be told"
            )
        out.append(hits[0])
    return out


def _gap_text(frames: np.ndarray, first: int) -> str:
    """``frames`` (sorted indices) as numbered runs ``"12-15, 40"``."""
    runs, start = [], 0
    for k in range(1, len(frames) + 1):
        if k == len(frames) or frames[k] != frames[k - 1] + 1:
            a, b = first + frames[start], first + frames[k - 1]
            runs.append(f"{a}" if a == b else f"{a}-{b}")
            start = k
    return ", ".join(runs[:5]) + (", ..." if len(runs) > 5 else "")


def load_c3d(
    files: str | Path | Sequence[str | Path],
    markers: Sequence[str] | None = None,
    *,
    labels: Sequence[str] | None = None,
    label_names: Sequence[str] | None = None,
    downsample: int = 1,
    gaps: str = "frames",
) -> MarkerTrials:
    """Read C3D recordings' marker trajectories as labelled trials.

    Args:
        files: a folder (its ``*.c3d`` files, sorted by name), a file, or a sequence of either.
        markers: the marker labels to keep, in that order; default all markers of the first
            file, which every file must then have.
        labels: one label per file, in the order of ``files``; default: each file's folder name.
        label_names: the labels in code order (default: in order of first appearance).
        downsample: keep every ``downsample``-th frame, from the first (>= 1).
        gaps: a frame in which a chosen marker is missing (occluded): ``"frames"`` (default):
            the whole row is NaN, a missing observation, as the toolkit's models and gap
            recovery take them (they refuse rows that are only partly NaN); ``"markers"``: only
            that marker's three columns are NaN; ``"error"``: refused, naming marker and
            frames.

    Returns:
        :class:`MarkerTrials` (a :class:`~.cmu.MotionTrials`): ``sequences`` J ``[T_j, 3 M]``
        float64 (``ceil(T / downsample)`` rows; NaN where missing, see ``gaps``), ``features``
        ``"marker.x"``, ``"marker.y"``, ``"marker.z"`` per marker, ``fps`` (the files' rate /
        ``downsample``), ``trials`` (file names without ``.c3d``), ``missing = []`` (an absent
        file is an error), ``missing_frames`` (per trial and marker) and ``units``.

    Raises:
        FileNotFoundError: a file or folder that does not exist, a folder without C3D files.
        ImportError: ``ezc3d`` is not installed.
        TypeError: ``files``, ``markers`` or ``labels`` of the wrong kind.
        ValueError: naming the file: an unreadable or malformed file (:func:`read_c3d`), a
            marker asked for that the file lacks (or labels twice), a marker missing in every
            frame, (``markers=None``) other markers than the first file's, a frame rate or
            units other than the first file's, a gap with ``gaps="error"``; a bad ``labels``,
            ``label_names``, ``downsample`` or ``gaps``.
    """
    check_choice(gaps, "gaps", C3D_GAPS)
    downsample = check_downsample(downsample)
    if isinstance(markers, str):
        raise TypeError(f"markers must be a sequence of marker labels, not a string: {markers!r}")
    paths = recording_files(files, ".c3d", "C3D")
    names, codes = recording_labels(paths, labels, label_names)
    trials = trial_names(paths)
    sequences, counts = [], {}
    chosen: list[str] | None = None if markers is None else [str(m) for m in markers]
    first: tuple[Path, C3dMarkers] | None = None
    for path, trial in zip(paths, trials, strict=True):
        data = read_c3d(path)
        if first is None:
            first = (path, data)
            if chosen is None:
                twice = sorted({m for m in data.labels if data.labels.count(m) > 1})
                if twice:
                    raise ValueError(f"C3D file {path}: markers {twice} are labelled twice")
                chosen = list(data.labels)
        else:
            check_rate(path, data.fps, first[0], first[1].fps, "C3D")
            if data.units != first[1].units:
                raise ValueError(
                    f"C3D file {path}: units {data.units!r}, but {first[0]} has "
                    f"{first[1].units!r}; the files of one call must share units"
                )
            if markers is None and set(data.labels) != set(chosen):
                raise ValueError(
                    f"C3D file {path}: its markers differ from those of {first[0]} (the first "
                    f"file): only here {sorted(set(data.labels) - set(chosen))}, only there "
                    f"{sorted(set(chosen) - set(data.labels))}"
                )
        x = data.positions[:, _choose(path, data, chosen)]  # [T, M, 3]
        gone = np.isnan(x).any(-1)  # [T, M]: a marker with any coordinate NaN is missing
        counts[trial] = {m: int(n) for m, n in zip(chosen, gone.sum(0), strict=True)}
        never = [m for m, n in counts[trial].items() if n == len(x)]
        if never:
            raise ValueError(
                f"C3D file {path}: markers {never} are missing in all {len(x)} frames; a marker "
                "never seen carries nothing (leave it out of markers)"
            )
        if gaps == "error" and gone.any():
            m = int(np.flatnonzero(gone.any(0))[0])
            raise ValueError(
                f"C3D file {path}: marker {chosen[m]!r} is missing in frames "
                f"{_gap_text(np.flatnonzero(gone[:, m]), data.first_frame)} "
                f"({int(gone[:, m].sum())} frames); pass gaps='frames' to read them as missing "
                "(NaN) frames"
            )
        x = x.copy()
        if gaps == "frames":
            x[gone.any(1)] = np.nan
        else:
            x[gone] = np.nan
        values = x[::downsample].reshape(-1, 3 * len(chosen))
        sequences.append(torch.as_tensor(values, dtype=torch.float64))
    assert first is not None and chosen is not None  # recording_files gives at least one file
    return MarkerTrials(
        sequences=sequences,
        labels=torch.tensor(codes, dtype=torch.long),
        label_names=names,
        trials=trials,
        features=[f"{m}.{a}" for m in chosen for a in "xyz"],
        fps=first[1].fps / downsample,
        missing=[],
        missing_frames=counts,
        units=first[1].units,
    )
