"""MSRC-12 Kinect gestures (Fothergill et al., CHI 2012): the real data of the action-recognition
experiment (thesis Sec. 3.6, Table 3.3, which used Kinect skeletons of similar actions).

Two sources give the same :class:`MSRC12` instances, windows of skeletons cut around annotated
action points:

- :func:`load_msrc12_npz`: the development archive ``../shared/data/msrc12_dev.npz`` (already cut:
  ``positions [n, 36, 20, 3]`` at 10 frames/s, the action point at frame 30);
- :func:`load_msrc12_folder`: a folder of the original release, read by
  :func:`read_msrc12_recording`, and cut by the same rule at any frame rate.

The original release format, as this reader assumes it:

- ``<name>.csv``: one frame per line, ``81`` numbers separated by spaces (commas and semicolons are
  accepted too): a timestamp in milliseconds, then for each of the 20 joints (in the order of
  :data:`JOINTS`, Kinect SDK v1) ``x y z w``, positions in metres and ``w`` the tracking value,
  kept as :attr:`MSRC12Recording.state` and otherwise unused. Frames whose 20 positions are all
  zero carry no skeleton (the Kinect had not yet found the person, as at the start of some
  recordings) and are dropped. A joint at ``(0, 0, 0)`` in a frame whose other joints are
  tracked is a joint the Kinect lost: an error (or, with ``partial_frames="drop"``, the frame is
  dropped too), never a position. Coordinates beyond +-:data:`MAX_POSITION_M` metres, non-finite
  values and timestamps that do not increase are errors naming the file, line, frame and joint.
- ``<name>.tagstream``: a header line (``XQPCTick;Tag``) and one line ``<tick>;<tag>`` per action
  point, the tag being the gesture id (``7``, or with a prefix such as ``G7``). Ticks count at
  :data:`TICKS_PER_SECOND` = 49875 Hz on the clock of the csv timestamps:
  ``time_ms = tick * 1000 / 49875``. This is the conversion of the MATLAB loader shipped with the
  data set (which also rounds to whole milliseconds; here the time is kept exact, a difference of
  at most 0.5 ms). A recording none of whose action points falls within its csv time span
  contradicts the assumption and is an error.
- File names ``P<a>_<b>_<gesture>[<variant>]_p<person>``, e.g. ``P1_1_1_p06`` or ``P1_1_12A_p21``:
  ``P<a>_<b>`` codes the instruction the person was given (text, images, video, ...; kept as the
  string :attr:`MSRC12Recording.instruction`, not interpreted), then the gesture id (1-12) with
  an optional letter, then the person (``p06``).

Gesture ids and names are in :data:`GESTURES`. The development archive holds six of them
(2, 3, 6, 7, 8, 12); labels are coded ``0 .. K-1`` in increasing order of the ids present.

Features of the skeletons (joint positions relative to the hip centre, and a PCA fitted on the
training persons' frames only) are in :mod:`hgpdm_torch.datasets.kinect_features`.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..progress import tqdm
from ..validation import as_tensor, check_choice

__all__ = [
    "GESTURES",
    "JOINTS",
    "MAX_POSITION_M",
    "MSRC12",
    "MSRC12Recording",
    "MissingTagstreamError",
    "TICKS_PER_SECOND",
    "load_msrc12_folder",
    "load_msrc12_npz",
    "read_msrc12_recording",
]

JOINTS: tuple[str, ...] = (
    "hip_centre", "spine", "shoulder_centre", "head",
    "shoulder_left", "elbow_left", "wrist_left", "hand_left",
    "shoulder_right", "elbow_right", "wrist_right", "hand_right",
    "hip_left", "knee_left", "ankle_left", "foot_left",
    "hip_right", "knee_right", "ankle_right", "foot_right",
)  # fmt: skip
"""The 20 Kinect SDK v1 joints, in file order."""

GESTURES: dict[int, str] = {
    1: "lift outstretched arms",
    2: "crouch",
    3: "push right",
    4: "goggles",
    5: "wind it up",
    6: "shoot",
    7: "bow",
    8: "throw",
    9: "had enough",
    10: "change weapon",
    11: "beat both",
    12: "kick",
}
"""MSRC-12 gesture id -> short name."""

TICKS_PER_SECOND = 49875
"""Rate of the tagstream's ``XQPCTick`` clock (see the module docstring)."""

MAX_POSITION_M = 100.0
"""Largest joint coordinate accepted, in metres. The Kinect sees a person up to a few metres
away (the development archive stays within 4.1 m), so a larger value is a corrupted one."""

_VALUES_PER_FRAME = 1 + 4 * len(JOINTS)
_NAME = re.compile(r"^(P\d+_\d+)_(\d+)([A-Za-z]*)_(p\d+)$")
_TAG = re.compile(r"^[A-Za-z_]*(\d+)$")
_SPLIT = re.compile(r"[\s,;]+")


class MissingTagstreamError(FileNotFoundError, ValueError):
    """A recording's ``.tagstream`` file is missing (both a ``FileNotFoundError`` and a
    ``ValueError``, as the other format errors of this module)."""


# ------------------------------------------------------------------------------------------
# Instances
# ------------------------------------------------------------------------------------------


@dataclass
class MSRC12:
    """Gesture instances: skeleton windows around action points.

    Attributes:
        positions: ``[n, T, 20, 3]`` (float64) joint positions in metres, joints as in
            :data:`JOINTS`.
        labels: ``[n]`` (long) class codes ``0 .. K-1``.
        gesture_ids: the K MSRC-12 gesture ids, ``gesture_ids[labels[i]]`` is instance i's.
        names: the K gesture names.
        person: ``n`` person ids (``"p04"``, ...).
        sequence: ``n`` names of the recordings the instances were cut from.
        fps: frame rate of ``positions``.
        action_frame: index of the action point in every window.
        dropped: windows that could not be cut (outside the recording, or across a gap), in
            words; empty for the development archive.
    """

    positions: torch.Tensor
    labels: torch.Tensor
    gesture_ids: tuple[int, ...]
    names: tuple[str, ...]
    person: list[str]
    sequence: list[str]
    fps: float
    action_frame: int
    dropped: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def num_classes(self) -> int:
        """K, the number of gestures."""
        return len(self.gesture_ids)

    @property
    def persons(self) -> list[str]:
        """The distinct person ids, sorted."""
        return sorted(set(self.person))

    def groups(self) -> np.ndarray:
        """``[n]`` (int) index of each instance's person in :attr:`persons`: the groups of a
        leave-persons-out split (e.g. scikit-learn ``GroupKFold``)."""
        index = {p: i for i, p in enumerate(self.persons)}
        return np.array([index[p] for p in self.person], dtype=int)

    def subset(self, index: Any) -> MSRC12:
        """The instances at ``index`` (integer indices or a boolean mask ``[n]``), same K."""
        idx = np.arange(len(self))[np.asarray(index)]
        return MSRC12(
            positions=self.positions[torch.as_tensor(idx, dtype=torch.long)],
            labels=self.labels[torch.as_tensor(idx, dtype=torch.long)],
            gesture_ids=self.gesture_ids,
            names=self.names,
            person=[self.person[i] for i in idx],
            sequence=[self.sequence[i] for i in idx],
            fps=self.fps,
            action_frame=self.action_frame,
            dropped=list(self.dropped),
        )


def _code_gestures(gesture: np.ndarray, source: str) -> tuple[torch.Tensor, tuple[int, ...]]:
    unknown = sorted(set(gesture.tolist()) - set(GESTURES))
    if unknown:
        raise ValueError(f"{source}: unknown gesture ids {unknown}; MSRC-12 has ids 1-12")
    ids = tuple(sorted(set(gesture.tolist())))
    code = {g: k for k, g in enumerate(ids)}
    return torch.tensor([code[g] for g in gesture.tolist()], dtype=torch.long), ids


def load_msrc12_npz(
    path: str | Path = "../shared/data/msrc12_dev.npz",
    *,
    fps: float = 10.0,
    action_frame: int = 30,
) -> MSRC12:
    """Load the development archive of cut MSRC-12 instances.

    Args:
        path: ``.npz`` with ``positions`` ``[n, T, 20, 3]`` (metres), ``gesture`` ``[n]``
            (MSRC-12 ids), ``person`` ``[n]`` and ``sequence`` ``[n]`` (strings).
        fps: frame rate of the windows (10 for the shared file).
        action_frame: index of the action point in each window (30 for the shared file: 3.0 s
            before to 0.5 s after it).

    Returns:
        :class:`MSRC12` with labels coded in increasing order of the gesture ids present.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: a missing key, wrong shapes, unknown gesture ids, or positions that are not
            finite, beyond +-:data:`MAX_POSITION_M` metres, or a joint at ``(0, 0, 0)`` (the
            Kinect's mark of a joint it did not track), naming the instance, frame and joint.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"MSRC-12 archive not found: {path}")
    with np.load(path, allow_pickle=False) as archive:
        missing = [k for k in ("positions", "gesture", "person", "sequence") if k not in archive]
        if missing:
            raise ValueError(f"{path} lacks the arrays {missing}")
        positions = archive["positions"]
        gesture, person, sequence = (archive[k] for k in ("gesture", "person", "sequence"))
    n = positions.shape[0]
    if positions.ndim != 4 or positions.shape[2:] != (len(JOINTS), 3):
        raise ValueError(f"{path}: positions must be [n, T, 20, 3], got {positions.shape}")
    for key, arr in (("gesture", gesture), ("person", person), ("sequence", sequence)):
        if arr.shape != (n,):
            raise ValueError(f"{path}: {key} must be [{n}], one per instance, got {arr.shape}")
    if not 0 <= action_frame < positions.shape[1]:
        raise ValueError(f"action_frame must index the {positions.shape[1]} frames")
    x = as_tensor(positions, f"{path}[positions]", dtype=torch.float64)
    _check_positions(positions, str(path), lambda i: f"instance {i[0]}, frame {i[1]}")
    labels, ids = _code_gestures(gesture.astype(int), str(path))
    return MSRC12(
        positions=x,
        labels=labels,
        gesture_ids=ids,
        names=tuple(GESTURES[g] for g in ids),
        person=[str(p) for p in person],
        sequence=[str(s) for s in sequence],
        fps=float(fps),
        action_frame=int(action_frame),
    )


# ------------------------------------------------------------------------------------------
# The original release: csv + tagstream
# ------------------------------------------------------------------------------------------


@dataclass
class MSRC12Recording:
    """One recording of the original release.

    Attributes:
        name: the file stem, e.g. ``"P1_1_12A_p21"``.
        time_ms: ``[F]`` csv timestamps (milliseconds) of the tracked frames, increasing.
        positions: ``[F, 20, 3]`` joint positions (metres).
        state: ``[F, 20]`` the fourth value of every joint (tracking value ``w``).
        tag_ms: ``[A]`` action points in milliseconds on the csv clock.
        tag_gesture: ``[A]`` (int) the gesture id of every action point.
        instruction: ``"P<a>_<b>"`` from the file name (``None`` if the name does not parse).
        gesture: gesture id from the file name (or ``None``).
        variant: letter after the gesture id in the file name (``""`` if none, or ``None``).
        person: person id from the file name, e.g. ``"p21"`` (or ``None``).
        untracked: frames dropped because all their positions were zero, or (with
            ``partial_frames="drop"``) some joint was.
        partial: of these, the frames dropped because some but not all joints were at zero.
    """

    name: str
    time_ms: np.ndarray
    positions: np.ndarray
    state: np.ndarray
    tag_ms: np.ndarray
    tag_gesture: np.ndarray
    instruction: str | None
    gesture: int | None
    variant: str | None
    person: str | None
    untracked: int = 0
    partial: int = 0


def _nonblank(path: Path) -> list[tuple[int, str]]:
    """``(line number, stripped text)`` of the non-blank lines."""
    try:
        text = path.read_text()
    except UnicodeDecodeError as err:
        raise ValueError(f"{path} is not a text file: {err}") from err
    return [(i, s) for i, line in enumerate(text.splitlines(), 1) if (s := line.strip())]


def _column(col: int) -> str:
    """The quantity in column ``col`` of a skeleton csv line, in words."""
    if col == 0:
        return "the timestamp"
    joint, axis = divmod(col - 1, 4)
    return f"joint {JOINTS[joint]!r} {'xyzw'[axis]}"


def _check_positions(
    positions: np.ndarray,
    source: str,
    where: Callable[[tuple[int, ...]], str],
    *,
    lost: bool = True,
) -> None:
    """Refuse joint coordinates beyond :data:`MAX_POSITION_M` and (``lost``) joints at
    ``(0, 0, 0)``.

    ``positions`` is ``[..., 20, 3]`` and finite; ``where(index)`` names the frame of the
    leading ``index``. The Kinect puts a joint it did not track at the sensor's origin, where
    no body part can be: such a joint is a missing one, never a position.
    """
    far = np.abs(positions) > MAX_POSITION_M
    if far.any():
        *at, joint, axis = np.argwhere(far)[0]
        raise ValueError(
            f"{source}, {where(tuple(at))}: joint {JOINTS[joint]!r} {'xyz'[axis]} is "
            f"{positions[(*at, joint, axis)]:g} m; coordinates beyond +-{MAX_POSITION_M:g} m "
            f"are not a person in front of a Kinect"
        )
    at_origin = (positions == 0).all(-1)
    if lost and at_origin.any():
        *at, joint = np.argwhere(at_origin)[0]
        raise ValueError(
            f"{source}, {where(tuple(at))}: joint {JOINTS[joint]!r} is at (0, 0, 0), the "
            f"Kinect's mark of a joint it did not track; a missing joint is never read as a "
            f"position"
        )


def _read_csv(path: Path) -> tuple[np.ndarray, list[int]]:
    """The ``[F, 81]`` numbers of a skeleton csv and the line number of each frame, every line
    checked."""
    lines = _nonblank(path)
    if not lines:
        raise ValueError(f"{path} is empty; expected one frame of {_VALUES_PER_FRAME} numbers "
                         f"per line")  # fmt: skip
    rows = [_SPLIT.split(text) for _, text in lines]
    for frame, ((number, _), row) in enumerate(zip(lines, rows, strict=True), 1):
        if len(row) != _VALUES_PER_FRAME:
            raise ValueError(
                f"{path}, line {number} (frame {frame}): expected {_VALUES_PER_FRAME} numbers "
                f"(a timestamp and x y z w of each of the 20 joints), got {len(row)}"
            )
    try:
        values = np.array(rows, dtype=np.float64)
    except ValueError:  # find the offending line
        for frame, ((number, _), row) in enumerate(zip(lines, rows, strict=True), 1):
            for col, item in enumerate(row):
                try:
                    float(item)
                except ValueError:
                    raise ValueError(
                        f"{path}, line {number} (frame {frame}): value {col + 1} "
                        f"({_column(col)}) is {item!r}, not a number"
                    ) from None
        raise
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise ValueError(
            f"{path}, line {lines[row][0]} (frame {row + 1}): value {col + 1} ({_column(col)}) "
            f"is {values[row, col]}; expected finite numbers"
        )
    step = np.diff(values[:, 0])
    if (step <= 0).any():
        row = int(np.argmax(step <= 0)) + 1
        raise ValueError(
            f"{path}, line {lines[row][0]} (frame {row + 1}): timestamp {values[row, 0]:g} ms "
            f"does not increase (previous {values[row - 1, 0]:g} ms)"
        )
    return values, [number for number, _ in lines]


def _read_tagstream(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Action points ``(time_ms [A], gesture id [A])`` of a tagstream file."""
    lines = _nonblank(path)
    if lines and not lines[0][1].split(";")[0].strip().isdigit():
        header, lines = lines[0], lines[1:]
        if len(header[1].split(";")) != 2:
            raise ValueError(
                f"{path}, line {header[0]}: expected a header 'XQPCTick;Tag', got {header[1]!r}"
            )
    if not lines:
        raise ValueError(f"{path} holds no action points; expected lines '<tick>;<gesture id>'")
    ticks, gestures = [], []
    for number, text in lines:
        parts = [p.strip() for p in text.split(";")]
        tag = _TAG.match(parts[1]) if len(parts) == 2 else None
        if len(parts) != 2 or not parts[0].isdigit() or tag is None:
            raise ValueError(
                f"{path}, line {number}: expected '<tick>;<gesture id>' (a non-negative integer "
                f"tick and an integer id such as 7 or G7), got {text!r}"
            )
        gesture = int(tag.group(1))
        if gesture not in GESTURES:
            raise ValueError(f"{path}, line {number}: gesture id {gesture} is not in 1-12")
        ticks.append(int(parts[0]))
        gestures.append(gesture)
    time_ms = np.array(ticks, dtype=np.float64) * 1000.0 / TICKS_PER_SECOND
    return time_ms, np.array(gestures, dtype=int)


def read_msrc12_recording(
    csv_path: str | Path,
    tagstream_path: str | Path | None = None,
    *,
    partial_frames: str = "error",
) -> MSRC12Recording:
    """Read one recording of the original MSRC-12 release (format in the module docstring).

    Args:
        csv_path: the skeleton ``.csv`` file.
        tagstream_path: its action points (default: ``<csv stem>.tagstream`` beside it).
        partial_frames: a frame in which some joints are tracked and another is at
            ``(0, 0, 0)`` (the Kinect's mark of a joint it lost): ``"error"`` (default), or
            ``"drop"``: drop the frame as an untracked one (counted in
            :attr:`MSRC12Recording.partial`).

    Returns:
        :class:`MSRC12Recording` with the tracked frames and the action points in ms.

    Raises:
        FileNotFoundError: no csv file.
        MissingTagstreamError: no tagstream file.
        ValueError: naming the file, line and frame (and the joint or timestamp): a line
            without 81 numbers, a non-numeric or non-finite value, a coordinate beyond
            +-:data:`MAX_POSITION_M` metres, a lost joint in a tracked frame (with
            ``partial_frames="error"``), timestamps that do not increase; a malformed tagstream
            line or an unknown gesture id; an empty file (no frames, no action points, or no
            tracked frame); a bad ``partial_frames``.
    """
    check_choice(partial_frames, "partial_frames", ("error", "drop"))
    csv_path = Path(csv_path)
    if not csv_path.is_file():
        raise FileNotFoundError(f"MSRC-12 recording not found: {csv_path}")
    tag_path = Path(tagstream_path or csv_path.with_suffix(".tagstream"))
    if not tag_path.is_file():
        raise MissingTagstreamError(
            f"{csv_path} has no tagstream file {tag_path} (the action points are needed)"
        )
    values, line_of = _read_csv(csv_path)
    joints = values[:, 1:].reshape(-1, len(JOINTS), 4)
    tracked = (joints[..., :3] != 0).any(axis=(1, 2))
    partial = tracked & (joints[..., :3] == 0).all(-1).any(-1)
    if partial_frames == "drop":
        tracked &= ~partial
    if not tracked.any():
        why = "all positions are zero" + (", or some joint's" if partial.any() else "")
        raise ValueError(f"{csv_path} has no tracked frame ({why})")

    def where(at: tuple[int, ...]) -> str:
        return f"line {line_of[at[0]]} (frame {at[0] + 1})"

    _check_positions(joints[..., :3], str(csv_path), where, lost=False)  # every frame
    # lost joints only in the frames kept: untracked ones (all zero) and dropped ones aside
    rows = np.flatnonzero(tracked)
    _check_positions(joints[rows, :, :3], str(csv_path), lambda at: where((rows[at[0]],)))
    tag_ms, tag_gesture = _read_tagstream(tag_path)
    match = _NAME.match(csv_path.stem)
    instruction, gesture, variant, person = (
        (match.group(1), int(match.group(2)), match.group(3), match.group(4))
        if match
        else (None, None, None, None)
    )
    return MSRC12Recording(
        name=csv_path.stem,
        time_ms=values[tracked, 0],
        positions=joints[tracked, :, :3],
        state=joints[tracked, :, 3],
        tag_ms=tag_ms,
        tag_gesture=tag_gesture,
        instruction=instruction,
        gesture=gesture,
        variant=variant,
        person=person,
        untracked=int((~tracked).sum()),
        partial=int(partial.sum()),  # 0 unless dropped: with "error" they were refused
    )


def _frames(seconds: float, fps: float, name: str) -> int:
    if not (isinstance(seconds, numbers.Real) and 0 <= seconds < math.inf):
        raise ValueError(f"{name} must be a finite number of seconds >= 0, got {seconds!r}")
    frames = seconds * fps
    if abs(frames - round(frames)) > 1e-6:
        raise ValueError(f"{name} * fps must be a whole number of frames, got {frames:g}")
    return round(frames)


def _resample(
    time_ms: np.ndarray, values: np.ndarray, at_ms: np.ndarray, method: str
) -> np.ndarray:
    """``values [F, ...]`` at the times ``at_ms [S]`` (within ``time_ms``) -> ``[S, ...]``."""
    if len(time_ms) == 1:
        return np.repeat(values, len(at_ms), axis=0)
    i = np.clip(np.searchsorted(time_ms, at_ms, side="right") - 1, 0, len(time_ms) - 2)
    w = (at_ms - time_ms[i]) / (time_ms[i + 1] - time_ms[i])
    if method == "nearest":
        return values[np.where(w > 0.5, i + 1, i)]
    w = w.reshape(-1, *([1] * (values.ndim - 1)))
    return (1.0 - w) * values[i] + w * values[i + 1]


def load_msrc12_folder(
    folder: str | Path,
    fps: float = 10.0,
    before: float = 3.0,
    after: float = 0.5,
    *,
    gestures: Sequence[int] | None = None,
    method: str = "linear",
    max_gap: float = 0.2,
    progress: bool = False,
    partial_frames: str = "error",
) -> MSRC12:
    """Cut windows around every action point of a folder of original MSRC-12 recordings.

    Every ``*.csv`` in ``folder`` (not its subfolders, in sorted order) is read with its
    ``.tagstream`` (:func:`read_msrc12_recording`). Around an action point at time ``a`` the
    window samples the skeleton at ``a + (k - n_before) / fps`` for ``k = 0 .. n_before +
    n_after`` (``n_before = before * fps``, ``n_after = after * fps``, whole numbers), so the
    action point is frame ``n_before``: the defaults give the layout of the development archive
    (36 frames at 10 frames/s, action point at frame 30). The csv frames (~30 frames/s, not
    evenly spaced) are resampled by linear interpolation in time between the two frames around
    each sample time (``method="linear"``) or by the frame with the nearest timestamp
    (``"nearest"``, ties to the earlier). A window is dropped (and listed in
    :attr:`MSRC12.dropped`) when a sample time lies before the first or after the last tracked
    frame, or between two tracked frames more than ``max_gap`` seconds apart.

    Args:
        folder: the folder of recordings.
        fps: frame rate of the windows.
        before: seconds before the action point.
        after: seconds after the action point.
        gestures: keep only these gesture ids (default: all found).
        method: ``"linear"`` or ``"nearest"``.
        max_gap: longest gap (s) between tracked frames a window may span.
        progress: tqdm bar over the recordings.
        partial_frames: frames with a lost joint (at ``(0, 0, 0)``): ``"error"`` or ``"drop"``
            (then a window across them is interpolated, or dropped across a gap over
            ``max_gap``), as in :func:`read_msrc12_recording`.

    Returns:
        :class:`MSRC12`, labels coded in increasing order of the gesture ids kept, instances in
        file order then time order.

    Raises:
        FileNotFoundError: the folder does not exist or holds no csv file.
        MissingTagstreamError: a recording without its tagstream.
        ValueError: malformed files (see :func:`read_msrc12_recording`), a file name without the
            person (``..._p<digits>``), an action point whose gesture id differs from the file
            name's, a recording none of whose action points lies within its time span (see the
            module docstring on the tick clock), no window at all, or bad arguments.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"MSRC-12 folder not found: {folder}")
    if not (isinstance(fps, numbers.Real) and 0 < fps < math.inf):
        raise ValueError(f"fps must be a positive finite number, got {fps!r}")
    if not (isinstance(max_gap, numbers.Real) and 0 < max_gap <= math.inf):
        raise ValueError(f"max_gap must be a positive number of seconds, got {max_gap!r}")
    check_choice(method, "method", ("linear", "nearest"))
    check_choice(partial_frames, "partial_frames", ("error", "drop"))
    n_before, n_after = _frames(before, fps, "before"), _frames(after, fps, "after")
    keep = None if gestures is None else {int(g) for g in gestures}
    files = sorted(folder.glob("*.csv"))
    if not files:
        raise FileNotFoundError(f"no MSRC-12 recording (*.csv) in {folder}")
    offsets_ms = (np.arange(n_before + n_after + 1) - n_before) * 1000.0 / fps
    windows, gesture, person, sequence, dropped = [], [], [], [], []
    for path in tqdm(files, disable=not progress, desc="MSRC-12 recordings"):
        rec = read_msrc12_recording(path, partial_frames=partial_frames)
        if rec.person is None:
            raise ValueError(
                f"{path}: cannot read the person from the file name; expected "
                f"P<a>_<b>_<gesture>[letter]_p<person>.csv"
            )
        t = rec.time_ms
        inside = (rec.tag_ms >= t[0]) & (rec.tag_ms <= t[-1])
        if not inside.any():
            raise ValueError(
                f"{path}: none of its {len(rec.tag_ms)} action points "
                f"({rec.tag_ms.min():.0f}-{rec.tag_ms.max():.0f} ms) lies within the csv time span "
                f"{t[0]:.0f}-{t[-1]:.0f} ms; the tagstream ticks are read as "
                f"{TICKS_PER_SECOND} Hz on the csv's millisecond clock"
            )
        for a, (at, g) in enumerate(zip(rec.tag_ms, rec.tag_gesture, strict=True)):
            if rec.gesture is not None and g != rec.gesture:
                raise ValueError(
                    f"{path.with_suffix('.tagstream')}: action point {a + 1} has gesture id {g}, "
                    f"the file name says {rec.gesture}"
                )
            if keep is not None and g not in keep:
                continue
            times = at + offsets_ms
            where = f"{rec.name} action point {a + 1} at {at:.0f} ms"
            if times[0] < t[0] or times[-1] > t[-1]:
                dropped.append(f"{where}: window outside the recording")
                continue
            i = np.searchsorted(t, times, side="left")  # first frame at or after each sample
            between = (t[np.clip(i, 0, len(t) - 1)] != times) & (i > 0)
            gaps = t[np.clip(i, 0, len(t) - 1)] - t[np.clip(i - 1, 0, len(t) - 1)]
            if (between & (gaps > 1000.0 * max_gap)).any():
                dropped.append(f"{where}: window spans a gap over {max_gap:g} s")
                continue
            windows.append(_resample(t, rec.positions, times, method))
            gesture.append(g)
            person.append(rec.person)
            sequence.append(rec.name)
    if not windows:
        raise ValueError(f"no window could be cut from the recordings in {folder}: {dropped[:3]}")
    labels, ids = _code_gestures(np.array(gesture), str(folder))
    return MSRC12(
        positions=torch.as_tensor(np.stack(windows), dtype=torch.float64),
        labels=labels,
        gesture_ids=ids,
        names=tuple(GESTURES[g] for g in ids),
        person=person,
        sequence=sequence,
        fps=float(fps),
        action_frame=n_before,
        dropped=dropped,
    )
