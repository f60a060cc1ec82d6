"""BVH motion-capture files (Biovision Hierarchy) as :class:`~.cmu.MotionTrials`.

A BVH file holds a skeleton (``HIERARCHY``: joints with an ``OFFSET`` and ``CHANNELS``, nested
``JOINT`` blocks, ``End Site`` leaves) and its motion (``MOTION``: ``Frames: N``,
``Frame Time: dt`` in seconds, then one line of numbers per frame, every joint's channels in the
order of the hierarchy). Vicon Blade/Shogun, MotionBuilder, OptiTrack Motive, Xsens and most
public conversions of the CMU database export it.

Why these readers: the hierarchy is parsed by ``bvhio`` (maintained, on PyPI: 1.5 released in
2025; it handles any channel order, ``End Site`` leaves, CRLF files, and refuses malformed
hierarchy blocks with the line). ``bvhio`` turns each frame's Euler channels into a quaternion as
it reads (in single precision), which loses the values as written: an angle of 200 degrees comes
back as another triple of angles for the same rotation, and a corrupted ``1e6`` as an arbitrary
one. So the motion lines, a plain table of numbers, are read here, as written, in double
precision: every value is then checked (finite, within :data:`~.mocap.MAX_ANGLE_DEGREES`), and a
joint angle keeps its own channel, as in the CMU AMC files.

Refused, naming the file (and line, frame and joint where there is one): no ``MOTION`` section
(a truncated file, on which ``bvhio`` would never return), a malformed hierarchy, a channel
other than ``X/Y/Zposition``, ``X/Y/Zrotation`` or one given twice, joints of the same name,
``Frames:`` other than the number of frame lines, a frame line with another number of values
than the hierarchy's channels, a non-number or non-finite value, an angle beyond
+-:data:`~.mocap.MAX_ANGLE_DEGREES` or a position beyond +-:data:`~.mocap.MAX_LENGTH`, a frame
time that is not a positive finite number; in :func:`load_bvh` also a joint or channel asked for
that a file lacks (never read as a zero angle), files of different skeletons (the difference is
named) or frame rates.

Channel names are ``"joint.dof"`` with ``dof`` one of ``tx ty tz rx ry rz`` (for ``Xposition``
... ``Zrotation``), as the CMU loader's ``"bone.dof"``; the root joint's channels are
``"root.*"`` whatever its name in the file, as in CMU's files.

The helpers :func:`recording_files`, :func:`recording_labels` and :func:`trial_names` (files of a
folder, labels and trial names of users' recordings) serve the C3D loader as well.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..validation import check_choice
from .cmu import MotionTrials
from .mocap import MAX_ANGLE_DEGREES, MAX_LENGTH, Bone, Skeleton, text_lines
from .walkers import motion_features, wrap_angles

__all__ = ["BvhMotion", "BvhSkeleton", "load_bvh", "read_bvh"]

#: BVH channel name -> the CMU loader's dof name
_DOFS = {
    "Xposition": "tx",
    "Yposition": "ty",
    "Zposition": "tz",
    "Xrotation": "rx",
    "Yrotation": "ry",
    "Zrotation": "rz",
}
_ROTATIONS = ("rx", "ry", "rz")
#: frame rates of the files of one call may differ by this much (relative): exporters round the
#: frame time (``0.008333`` or ``0.0083333`` for 120 frames/s)
RATE_RTOL = 1e-3


@dataclass(frozen=True)
class BvhSkeleton:
    """A BVH hierarchy.

    Attributes:
        root: the root joint's name in the file.
        joints: joint names in file order (depth first, the root first; ``End Site`` leaves are
            not joints).
        parent: each non-root joint's parent.
        dofs: each joint's channels as dofs (``"tx"`` ... ``"rz"``), in the file's order (for
            rotations, the order of the intrinsic rotations: ``Zrotation Xrotation Yrotation``
            is ``R = Rz Rx Ry``).
        offsets: each joint's ``OFFSET`` ``[3]`` from its parent, in the file's length units
            (single precision, as ``bvhio`` holds them).
    """

    root: str
    joints: tuple[str, ...]
    parent: dict[str, str]
    dofs: dict[str, tuple[str, ...]]
    offsets: dict[str, np.ndarray]

    def channels(self) -> list[str]:
        """The ``C`` channel names ``"joint.dof"`` in the order of a frame line (root:
        ``"root.*"``)."""
        return [f"{_name(self, j)}.{d}" for j in self.joints for d in self.dofs[j]]

    def differences(self, other: BvhSkeleton) -> list[str]:
        """What tells ``other``'s structure (joints, parents, channels) from this one's; bone
        lengths (offsets) may differ, as between people. Empty when the same."""
        out = []
        mine, theirs = set(self.joints), set(other.joints)
        if mine != theirs:
            out.append(
                f"joints only in one: {sorted(mine - theirs)} against {sorted(theirs - mine)}"
            )
        elif self.joints != other.joints:
            out.append("the same joints in another order")
        if self.root != other.root:
            out.append(f"root {self.root!r} against {other.root!r}")
        for j in self.joints:
            if j not in theirs:
                continue
            if self.parent.get(j) != other.parent.get(j):
                out.append(
                    f"joint {j!r} has parent {self.parent.get(j)!r} against {other.parent.get(j)!r}"
                )
            if self.dofs[j] != other.dofs[j]:
                out.append(
                    f"joint {j!r} has channels {' '.join(self.dofs[j]) or 'none'} against "
                    f"{' '.join(other.dofs[j]) or 'none'}"
                )
        return out


def _name(skeleton: BvhSkeleton, joint: str) -> str:
    return "root" if joint == skeleton.root else joint


@dataclass
class BvhMotion:
    """A BVH file as written.

    Attributes:
        skeleton: its hierarchy.
        values: ``[T, C]`` (float64) the frame lines: positions in the file's length units,
            angles in degrees, as written.
        channels: the ``C`` names ``"joint.dof"`` (``skeleton.channels()``).
        frame_time: seconds per frame (> 0).
    """

    skeleton: BvhSkeleton
    values: np.ndarray
    channels: list[str]
    frame_time: float

    @property
    def fps(self) -> float:
        """Frames per second, ``1 / frame_time``."""
        return 1.0 / self.frame_time


def _motion_header(path: Path, lines: list[str]) -> int:
    """The index of the ``Frame Time:`` line, after ``MOTION`` and ``Frames:`` lines.

    Checked before ``bvhio`` reads the file: its line reader loops forever at the end of a file
    that stops before these lines.
    """
    filled = [(i, line.split()) for i, line in enumerate(lines) if line.strip()]
    for k, (_, tokens) in enumerate(filled):
        if tokens == ["MOTION"]:
            rest = [t for _, t in filled[k + 1 : k + 3]]
            if len(rest) == 2 and rest[0][0] == "Frames:" and rest[1][:2] == ["Frame", "Time:"]:
                return filled[k + 2][0]
            break
    raise ValueError(
        f"BVH file {path}: no 'MOTION' line followed by 'Frames:' and 'Frame Time:' lines "
        "(not a BVH file, or truncated)"
    )


def _hierarchy(path: Path):  # -> bvhio.BvhContainer
    try:
        import bvhio
    except ImportError as err:  # optional extra
        raise ImportError(
            "reading BVH files needs the bvhio package: pip install 'hgpdm-torch[data]'"
        ) from err
    try:
        return bvhio.readAsBvh(str(path), loadKeyFrames=False)
    except SyntaxError as err:
        # bvhio's line numbers do not count every line; the line's text does tell it
        at = f" at {err.text.strip()!r}" if isinstance(err.text, str) and err.text.strip() else ""
        raise ValueError(f"BVH file {path}: {err.msg}{at} (bvhio)") from None
    except (ValueError, IndexError) as err:
        raise ValueError(f"BVH file {path}: malformed hierarchy ({err})") from None


def _skeleton(path: Path, root) -> BvhSkeleton:  # root: bvhio.BvhJoint
    joints, parent, dofs, offsets = [], {}, {}, {}

    def visit(joint, up: str | None) -> None:
        name = joint.Name
        if name in dofs:
            raise ValueError(f"BVH file {path}: two joints are named {name!r}")
        if up is not None and name == "root":
            raise ValueError(
                f"BVH file {path}: a joint other than the root is named 'root'; channels of the "
                "root are named 'root.*', so this name is reserved for it"
            )
        bad = [c for c in joint.Channels if c not in _DOFS]
        if bad:
            raise ValueError(
                f"BVH file {path}: joint {name!r} has unknown channels {bad}; expected "
                f"{' '.join(_DOFS)}"
            )
        if len(set(joint.Channels)) != len(joint.Channels):
            raise ValueError(
                f"BVH file {path}: joint {name!r} gives a channel twice: {joint.Channels}"
            )
        joints.append(name)
        dofs[name] = tuple(_DOFS[c] for c in joint.Channels)
        offsets[name] = np.array([joint.Offset.x, joint.Offset.y, joint.Offset.z], dtype=float)
        if up is not None:
            parent[name] = up
        for child in joint.Children:
            visit(child, name)

    visit(root, None)
    return BvhSkeleton(root.Name, tuple(joints), parent, dofs, offsets)


def read_bvh(path: str | Path) -> BvhMotion:
    """Read a BVH file: its hierarchy (through ``bvhio``) and its frames, as written.

    Returns:
        :class:`BvhMotion`: the skeleton, ``values [T, C]`` (degrees and length units), channel
        names, frame time.

    Raises:
        FileNotFoundError: no such file.
        ImportError: ``bvhio`` is not installed.
        ValueError: naming the file (and the line, frame and joint of a bad value): see the
            module docstring.
    """
    path = Path(path)
    lines = text_lines(path, "BVH")
    header = _motion_header(path, lines)
    container = _hierarchy(path)
    skeleton = _skeleton(path, container.Root)
    time = float(container.FrameTime)
    if not (math.isfinite(time) and time > 0):
        raise ValueError(
            f"BVH file {path}: line {header + 1}: Frame Time must be a positive number of "
            f"seconds, got {lines[header].split()[2:]}"
        )
    channels = skeleton.channels()
    rows = [i for i in range(header + 1, len(lines)) if lines[i].strip()]
    if container.FrameCount < 1 or container.FrameCount != len(rows):
        raise ValueError(
            f"BVH file {path}: 'Frames: {container.FrameCount}' but {len(rows)} frame lines "
            "follow; the frame count must be the number of frame lines, at least one "
            "(truncated file?)"
        )
    values = np.empty((len(rows), len(channels)))
    for frame, i in enumerate(rows):
        tokens = lines[i].split()
        where = f"BVH file {path}: line {i + 1} (frame {frame + 1})"
        if len(tokens) != len(channels):
            raise ValueError(
                f"{where}: {len(tokens)} values, but the hierarchy has {len(channels)} channels"
            )
        try:
            values[frame] = [float(t) for t in tokens]
        except ValueError:
            bad = next(t for t in tokens if not _is_float(t))
            col = tokens.index(bad)
            raise ValueError(f"{where}: channel {channels[col]} is {bad!r}, not a number") from None
    _check_values(path, values, channels, rows, skeleton.root)
    return BvhMotion(skeleton, values, channels, time)


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _check_values(
    path: Path, values: np.ndarray, channels: list[str], rows: list[int], root: str
) -> None:
    """Refuse non-finite values, angles beyond :data:`MAX_ANGLE_DEGREES` and positions beyond
    :data:`MAX_LENGTH`, naming the first one's line, frame and joint (``rows``: each frame's
    line index; ``root``: the root joint's name in the file)."""
    rotation = np.array([c.rsplit(".", 1)[1] in _ROTATIONS for c in channels], dtype=bool)
    bound = np.where(rotation, MAX_ANGLE_DEGREES, MAX_LENGTH)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (np.abs(values) > bound)
    if not bad.any():
        return
    frame, col = np.argwhere(bad)[0]
    joint, dof = channels[col].rsplit(".", 1)
    joint = f"{root!r} (the root)" if joint == "root" else repr(joint)
    value = values[frame, col]
    where = f"BVH file {path}: line {rows[frame] + 1} (frame {frame + 1}): joint {joint} {dof}"
    if not np.isfinite(value):
        raise ValueError(f"{where} is {value}; values must be finite numbers")
    if rotation[col]:
        raise ValueError(
            f"{where} is {value:g} degrees; a joint angle beyond +-{MAX_ANGLE_DEGREES:g} "
            "degrees (ten turns) is not a physical value"
        )
    raise ValueError(
        f"{where} is {value:g} length units; a position beyond +-{MAX_LENGTH:g} is not a "
        "physical value"
    )


# ------------------------------------------------------------------------------------------
# Files, labels and trial names of users' recordings (also used by the C3D loader)
# ------------------------------------------------------------------------------------------


def recording_files(files: str | Path | Sequence[str | Path], suffix: str, kind: str) -> list[Path]:
    """The recordings to read: a folder (its ``*{suffix}`` files, any case, sorted by name), a
    file, or a sequence of either.

    Raises:
        FileNotFoundError: a file or folder that does not exist, or a folder without such files.
        ValueError: no file given, or a file given twice.
        TypeError: ``files`` not a path or a sequence of paths.
    """
    items = [files] if isinstance(files, str | Path) else files
    if not isinstance(items, Sequence) or not all(isinstance(f, str | Path) for f in items):
        raise TypeError(
            f"files must be a {kind} file or folder, or a sequence of them, got {files!r}"
        )
    if not items:
        raise ValueError(f"files: no {kind} file given")
    out: list[Path] = []
    for item in map(Path, items):
        if item.is_dir():
            found = sorted(p for p in item.iterdir() if p.is_file() and p.suffix.lower() == suffix)
            if not found:
                raise FileNotFoundError(f"no {kind} files (*{suffix}) in folder {item}")
            out += found
        elif item.is_file():
            out.append(item)
        else:
            raise FileNotFoundError(f"{kind} file not found: {item}")
    seen = [p.resolve() for p in out]
    twice = [str(p) for k, p in enumerate(out) if seen[k] in seen[:k]]
    if twice:
        raise ValueError(f"files: {twice} given twice")
    return out


def recording_labels(
    paths: Sequence[Path], labels: Sequence[str] | None, label_names: Sequence[str] | None
) -> tuple[tuple[str, ...], list[int]]:
    """The label names and each file's label index.

    Args:
        paths: the files.
        labels: one label per file; ``None``: each file's folder name.
        label_names: the labels in code order; ``None``: in order of first appearance.

    Raises:
        ValueError: not one label per file, or a label not in ``label_names``.
        TypeError: ``labels`` given as one string.
    """
    if labels is None:
        given = [p.resolve().parent.name for p in paths]
    else:
        if isinstance(labels, str):
            raise TypeError(f"labels must be one label per file, not a string: {labels!r}")
        given = [str(lab) for lab in labels]
        if len(given) != len(paths):
            raise ValueError(f"labels: {len(paths)} files but {len(given)} labels")
    names = tuple(map(str, label_names)) if label_names is not None else tuple(dict.fromkeys(given))
    for path, label in zip(paths, given, strict=True):
        if label not in names:
            raise ValueError(f"labels: label {label!r} of {path} is not in label_names {names}")
    return names, [names.index(label) for label in given]


def trial_names(paths: Sequence[Path]) -> list[str]:
    """Each file's name without its suffix; the whole path without it if two names collide."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [str(p.with_suffix("")) for p in paths]


def check_rate(path: Path, fps: float, first: Path, first_fps: float, kind: str) -> None:
    """Refuse a ``kind`` file whose frame rate is not that of the first file of the call
    (within :data:`RATE_RTOL`)."""
    if abs(fps - first_fps) > RATE_RTOL * first_fps:
        raise ValueError(
            f"{kind} file {path}: {fps:g} frames/s, but {first} has {first_fps:g} frames/s; the "
            "files of one call must share a frame rate"
        )


def check_downsample(downsample: object) -> int:
    """``downsample`` as an int >= 1 (keep every ``downsample``-th frame)."""
    if isinstance(downsample, bool) or not isinstance(downsample, int) or downsample < 1:
        raise ValueError(f"downsample must be a positive int, got {downsample!r}")
    return downsample


# ------------------------------------------------------------------------------------------
# Loader
# ------------------------------------------------------------------------------------------

#: what :func:`load_bvh` returns per frame
BVH_FEATURES = ("motion", "channels")


def _select(path: Path, motion: BvhMotion, channels: Sequence[str] | None) -> list[int]:
    """Column indices of the channels asked for (``"joint"`` or ``"joint.dof"``; the root also
    as ``"root"``), in the order asked; all of them for ``None``."""
    if channels is None:
        return list(range(len(motion.channels)))
    if isinstance(channels, str):
        raise TypeError(f"channels must be a sequence of names, not a string: {channels!r}")
    sk = motion.skeleton
    names = {sk.root: "root", "root": "root"} | {j: j for j in sk.joints[1:]}
    keep: list[int] = []
    for asked in map(str, channels):
        whole = asked in names or "." not in asked  # a joint (whose name may hold a dot)
        joint, _, dof = (asked, "", "") if whole else asked.rpartition(".")
        if joint not in names:
            raise ValueError(
                f"BVH file {path}: joint {joint!r} (asked for in channels) is not in its "
                f"skeleton; its joints: {list(sk.joints)}"
            )
        prefix = names[joint]
        hits = [i for i, c in enumerate(motion.channels) if c.rsplit(".", 1)[0] == prefix]
        if dof:
            hits = [i for i in hits if motion.channels[i] == f"{prefix}.{dof}"]
        if not hits:
            own = [c.rsplit(".", 1)[1] for c in motion.channels if c.rsplit(".", 1)[0] == prefix]
            what = f"no channel {dof!r}" if dof else "no channels"
            raise ValueError(
                f"BVH file {path}: joint {joint!r} has {what} (asked for in channels); its "
                f"channels: {own}"
            )
        twice = [motion.channels[i] for i in hits if i in keep]
        if twice:
            raise ValueError(f"channels: {twice} asked for twice")
        keep += hits
    return keep


def _as_skeleton(path: Path, sk: BvhSkeleton) -> Skeleton:
    """The skeleton in the CMU loader's terms, for :func:`~.walkers.motion_features`.

    BVH rotation channels are intrinsic: ``Zrotation Xrotation Yrotation`` is
    ``R = Rz Rx Ry``, which is the fixed-axis sequence ``y, x, z`` (first applied first) that an
    ASF root ``order`` of ``RY RX RZ`` states: the reversed channel order.
    """
    root_dofs = sk.dofs[sk.root]
    if sorted(root_dofs) != ["rx", "ry", "rz", "tx", "ty", "tz"]:
        raise ValueError(
            f"BVH file {path}: the root joint {sk.root!r} has channels {list(root_dofs)}; the "
            "motion features need its three positions and three rotations (read its channels "
            "as they are with features='channels')"
        )
    rotations = [d for d in root_dofs if d in _ROTATIONS]
    bones = {}
    for k, joint in enumerate(sk.joints[1:], 1):
        offset = sk.offsets[joint]
        length = float(np.linalg.norm(offset))
        direction = offset / length if length > 0 else np.zeros(3)
        bones[joint] = Bone(k, joint, direction, length, np.zeros(3), dof=sk.dofs[joint])
    parent = {j: _name(sk, p) for j, p in sk.parent.items()}
    return Skeleton(sk.root, {"angle": "deg"}, ("tx", "ty", "tz", *rotations[::-1]), bones, parent)


def load_bvh(
    files: str | Path | Sequence[str | Path],
    *,
    labels: Sequence[str] | None = None,
    label_names: Sequence[str] | None = None,
    channels: Sequence[str] | None = None,
    downsample: int = 1,
    features: str = "motion",
) -> MotionTrials:
    """Read BVH recordings as labelled trials, like :func:`~.cmu.load_trials` reads CMU's.

    Args:
        files: a folder (its ``*.bvh`` files, sorted by name), a file, or a sequence of either.
        labels: one label per file, in the order of ``files``; default: each file's folder name.
        label_names: the labels in code order (default: in order of first appearance).
        channels: the channels to keep: ``"joint.dof"`` names or whole joints (all their
            channels; the root also as ``"root"``), in that order; default all. With
            ``features="motion"`` the root's six channels are always used.
        downsample: keep every ``downsample``-th frame, from the first (>= 1).
        features: ``"motion"`` (default): :func:`~.walkers.motion_features` as the CMU loader
            gives them: ``root.vx_heading``, ``root.vz_heading`` (the root's displacement
            between kept frames in its heading frame), ``root.ty``, ``root.yaw_rate``,
            ``root.pitch``, ``root.roll``, then every other joint angle in radians wrapped to
            ``[-pi, pi)`` (positions as they are), one row fewer than the kept frames. It takes
            ``y`` as up and the root's ``+z`` as forward (the CMU/VICON convention, kept by
            most BVH exporters), and needs the root's three positions and three rotations.
            ``"channels"``: the chosen channels themselves, angles in radians wrapped to
            ``[-pi, pi)``, positions in the file's length units, one row per kept frame.

    Returns:
        :class:`~.cmu.MotionTrials`: ``sequences`` J ``[T_j, F]`` float64 (BVH frames are never
        missing: no NaN rows), ``labels``, ``label_names``, ``trials`` (file names without
        ``.bvh``), ``features`` (the ``F`` names), ``fps = 1 / (frame time * downsample)``
        (of the first file), ``missing = []`` (an absent file is an error).

    Raises:
        FileNotFoundError: a file or folder that does not exist, a folder without BVH files.
        ImportError: ``bvhio`` is not installed.
        TypeError: ``files``, ``labels`` or ``channels`` of the wrong kind.
        ValueError: naming the file: a malformed file (:func:`read_bvh`), a joint or channel
            asked for that the file lacks, a skeleton other than the first file's (the
            difference named), a frame rate other than the first file's, a root without six
            channels (``features="motion"``), fewer than two kept frames; a bad ``labels``,
            ``label_names``, ``downsample`` or ``features``.
    """
    check_choice(features, "features", BVH_FEATURES)
    downsample = check_downsample(downsample)
    paths = recording_files(files, ".bvh", "BVH")
    names, codes = recording_labels(paths, labels, label_names)
    sequences, first, kept = [], None, None
    for path in paths:
        motion = read_bvh(path)
        keep = _select(path, motion, channels)
        if first is None:
            first = (path, motion)
        else:
            diff = first[1].skeleton.differences(motion.skeleton)
            if diff:
                raise ValueError(
                    f"BVH file {path}: its skeleton differs from that of {first[0]} (the first "
                    f"file): {'; '.join(diff)}"
                )
            check_rate(path, motion.fps, first[0], first[1].fps, "BVH")
        chosen = [motion.channels[i] for i in keep]
        if features == "motion":
            skeleton = _as_skeleton(path, motion.skeleton)
            chosen = [c for c in motion.channels if c.startswith("root.")] + [
                c for c in chosen if not c.startswith("root.")
            ]
            index = [motion.channels.index(c) for c in chosen]
            fps = first[1].fps
            try:
                values, kept = motion_features(
                    motion.values[:, index], chosen, skeleton, fps, fps / downsample
                )
            except ValueError as err:
                raise ValueError(f"BVH file {path}: {err}") from None
        else:
            x = motion.values[::downsample][:, keep]
            rotation = np.array([c.rsplit(".", 1)[1] in _ROTATIONS for c in chosen], dtype=bool)
            wrapped = wrap_angles(np.deg2rad(x))
            values, kept = np.where(rotation, wrapped, x), chosen
        sequences.append(torch.as_tensor(values, dtype=torch.float64))
    assert first is not None and kept is not None  # recording_files gives at least one file
    return MotionTrials(
        sequences=sequences,
        labels=torch.tensor(codes, dtype=torch.long),
        label_names=names,
        trials=trial_names(paths),
        features=list(kept),
        fps=first[1].fps / downsample,
        missing=[],
    )
