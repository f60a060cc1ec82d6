"""Reader for CMU motion-capture files (Acclaim ASF skeletons and AMC motions).

The CMU database (http://mocap.cs.cmu.edu/, used in thesis Sec. 2.4.1) stores a subject's
skeleton in an ``.asf`` file and each trial's joint angles in an ``.amc`` file:

- ASF: ``:units``, ``:root`` (``order`` of its channels), ``:bonedata`` (one ``begin ... end``
  block per bone: ``id``, ``name``, ``direction``, ``length``, ``axis``, optional ``dof`` and
  ``limits``) and ``:hierarchy`` (``parent child child ...`` lines);
- AMC: header lines (``#`` comments, ``:FULLY-SPECIFIED``, ``:DEGREES``), then for every frame
  its number on a line of its own followed by one ``bone v1 v2 ...`` line per moving bone, with
  as many values as the bone has degrees of freedom (the root: its ``order``).

:func:`read_amc` refuses what it cannot represent rather than guess: a frame (or a whole file)
without the line of a bone that moves in the skeleton is an error, never a zero angle or a value
carried over from another frame; so are joint angles beyond +-:data:`MAX_ANGLE_DEGREES` and frame
numbers that repeat, decrease or skip (skipped frames may instead be read as missing rows of NaN
with ``gaps="missing"``).

:func:`load_mocap` turns a trial into the ``[T, Dz]`` observation matrix the models take:
channel selection, down-sampling (the thesis used factors 4 and 10) and per-channel
normalisation. Channels are named ``"bone.dof"`` (e.g. ``"lfemur.rx"``, ``"root.tx"``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..validation import check_choice

__all__ = [
    "MAX_ANGLE_DEGREES",
    "MAX_LENGTH",
    "Bone",
    "MocapTrial",
    "Skeleton",
    "load_mocap",
    "read_amc",
    "read_asf",
]


@dataclass
class Bone:
    """One ASF bone: ``direction`` ``[3]`` (unit vector), ``length``, ``axis`` ``[3]`` (degrees)
    with its rotation ``axis_order``, degrees of freedom ``dof`` and their ``limits``."""

    id: int
    name: str
    direction: np.ndarray
    length: float
    axis: np.ndarray
    axis_order: str = "XYZ"
    dof: tuple[str, ...] = ()
    limits: list[tuple[float, float]] = field(default_factory=list)


@dataclass
class Skeleton:
    """A parsed ASF file.

    Attributes:
        name: the ``:name`` entry.
        units: ``:units`` entries (``mass``, ``length``, ``angle``).
        root_order: channels of the root, e.g. ``("tx", "ty", "tz", "rx", "ry", "rz")``: the
            order of its values in the AMC file and, for ``rx ry rz``, the sequence of the root's
            rotations about the fixed global axes.
        bones: bones by name, in file order.
        parent: parent bone name of every bone (``"root"`` for the root's children).
        root_axis: the root's ``axis`` entry, e.g. ``"XYZ"``: the rotation sequence of its
            pre-set ``root_orientation``.
        root_orientation: the root's pre-set ``orientation`` ``[3]`` (in ``units["angle"]``;
            zero in VICON/CMU files).
    """

    name: str
    units: dict[str, str]
    root_order: tuple[str, ...]
    bones: dict[str, Bone]
    parent: dict[str, str]
    root_axis: str = "XYZ"
    root_orientation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def channels(self) -> list[str]:
        """All channels ``"bone.dof"`` in a fixed order: the root's, then bones in file order."""
        names = [f"root.{d}" for d in self.root_order]
        for bone in self.bones.values():
            names += [f"{bone.name}.{d}" for d in bone.dof]
        return names


@dataclass
class MocapTrial:
    """A parsed AMC motion: ``values [T, C]`` for ``channels`` (``"bone.dof"``) at frames
    ``frame_numbers [T]``."""

    values: np.ndarray
    channels: list[str]
    frame_numbers: np.ndarray


def text_lines(path: str | Path, kind: str) -> list[str]:
    """The lines of a text file; ``FileNotFoundError`` if missing, ``ValueError`` if it is empty
    or not text."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{kind} file not found: {path}")
    try:
        text = path.read_text()
    except UnicodeDecodeError as err:
        raise ValueError(f"{kind} file {path} is not a text file ({err.reason})") from None
    if "\x00" in text:
        raise ValueError(f"{kind} file {path} is not a text file (it holds NUL bytes)")
    if not text.strip():
        raise ValueError(f"{kind} file {path} is empty")
    return text.splitlines()


def _floats(
    tokens: list[str], n: int, what: str, where: str, *, allow_inf: bool = False
) -> np.ndarray:
    """``n`` numbers from ``tokens``; finite unless ``allow_inf`` (never NaN)."""
    if len(tokens) != n:
        raise ValueError(f"{where}: {what} needs {n} numbers, got {len(tokens)}")
    try:
        values = np.array([float(t) for t in tokens])
    except ValueError:
        raise ValueError(f"{where}: {what} must be numbers, got {tokens}") from None
    if np.isnan(values).any() or not (allow_inf or np.isfinite(values).all()):
        kind = "numbers, not NaN" if allow_inf else "finite numbers"
        raise ValueError(f"{where}: {what} must be {kind}, got {tokens}")
    return values


def _value(tokens: list[str], what: str, where: str) -> str:
    if len(tokens) != 2:
        raise ValueError(f"{where}: {what} needs one value, got {tokens[1:]}")
    return tokens[1]


_ROOT_CHANNELS = {"tx", "ty", "tz", "rx", "ry", "rz"}
_ROTATIONS = ("rx", "ry", "rz")

#: Largest joint angle :func:`read_amc` accepts, in degrees (ten full turns). Real angles stay
#: well within it (the CMU walks reach about 440 degrees, in the root's heading), while a
#: corrupted value (``1e6``, ``1e300``) would otherwise wrap to an arbitrary angle.
MAX_ANGLE_DEGREES = 3600.0
_MAX_ANGLE_RAD = MAX_ANGLE_DEGREES * np.pi / 180.0

#: Largest translation or bone length (``tx ty tz l`` dofs) :func:`read_amc` accepts, in the
#: skeleton's length units (a CMU unit is 1/0.45 inch, so about 56 km): a sanity bound that
#: only corrupted values exceed.
MAX_LENGTH = 1e6

_MAX_SKIPPED = 432_000  # an hour at 120 frames/s: a longer jump is a corrupted frame number


def read_asf(path: str | Path) -> Skeleton:
    """Parse an Acclaim ASF skeleton file.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: an empty, binary or truncated file, one without a ``:root``
            ``order`` or without bones (not an ASF file), a malformed or non-finite entry (the
            message names the line), a bone without a name or twice, a ``dof`` other than
            ``rx ry rz tx ty tz l``, a hierarchy naming an unknown bone, or a bone missing from
            the hierarchy.
    """
    try:
        return _parse_asf(text_lines(path, "ASF"))
    except ValueError as err:
        if str(err).startswith("ASF file "):
            raise
        raise ValueError(f"ASF file {path}: {err}") from None


def _parse_asf(lines: list[str]) -> Skeleton:
    section, name, units = "", "", {}
    root_order: tuple[str, ...] = ()
    root_axis, root_orientation = "XYZ", np.zeros(3)
    bones: dict[str, Bone] = {}
    parent: dict[str, str] = {}
    bone: dict | None = None
    last_key = ""
    for lineno, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        where = f"line {lineno}"
        tokens = line.split()
        if tokens[0].startswith(":"):
            if bone is not None:
                raise ValueError(f"{where}: {tokens[0]} inside a bone block (no 'end')")
            section = tokens[0][1:].lower()
            if section == "name" and len(tokens) > 1:
                name = tokens[1]
            continue
        key = tokens[0].lower()
        if section == "units" and len(tokens) == 2:
            units[key] = tokens[1]
        elif section == "root" and key == "order":
            root_order = tuple(t.lower() for t in tokens[1:])
            if set(root_order) - _ROOT_CHANNELS or len(set(root_order)) != len(root_order):
                raise ValueError(f"{where}: root order must be distinct tx..rz: {line!r}")
        elif section == "root" and key == "axis":
            if len(tokens) != 2 or sorted(tokens[1].upper()) != ["X", "Y", "Z"]:
                raise ValueError(f"{where}: root axis must be an order of XYZ: {line!r}")
            root_axis = tokens[1].upper()
        elif section == "root" and key == "orientation":
            root_orientation = _floats(tokens[1:], 3, "orientation", where)
        elif section == "bonedata":
            if key == "begin":
                if bone is not None:
                    raise ValueError(f"{where}: 'begin' inside a bone block (no 'end')")
                bone = {"limits": []}
            elif key == "end":
                if bone is None or "name" not in bone:
                    raise ValueError(f"{where}: bone block without a name")
                if bone["name"] in bones:
                    raise ValueError(f"{where}: bone {bone['name']!r} defined twice")
                bones[bone["name"]] = Bone(
                    id=bone.get("id", len(bones) + 1),
                    name=bone["name"],
                    direction=bone.get("direction", np.zeros(3)),
                    length=bone.get("length", 0.0),
                    axis=bone.get("axis", np.zeros(3)),
                    axis_order=bone.get("axis_order", "XYZ"),
                    dof=bone.get("dof", ()),
                    limits=bone["limits"],
                )
                bone = None
            elif bone is None:
                raise ValueError(f"{where}: bone entry outside begin/end: {line!r}")
            elif key == "id":
                try:
                    bone["id"] = int(_value(tokens, "id", where))
                except ValueError as err:
                    raise ValueError(f"{where}: id must be an integer, got {tokens[1:]}") from err
            elif key == "name":
                bone["name"] = _value(tokens, "name", where)
            elif key == "direction":
                bone["direction"] = _floats(tokens[1:], 3, "direction", where)
            elif key == "length":
                bone["length"] = float(_floats(tokens[1:], 1, "length", where)[0])
                if bone["length"] < 0:
                    raise ValueError(f"{where}: length must be >= 0, got {tokens[1]}")
            elif key == "axis":
                bone["axis"] = _floats(tokens[1:4], 3, "axis", where)
                bone["axis_order"] = tokens[4] if len(tokens) > 4 else "XYZ"
            elif key == "dof":
                dof = tuple(t.lower() for t in tokens[1:])
                bad = set(dof) - {"rx", "ry", "rz", "tx", "ty", "tz", "l"}
                if bad:
                    raise ValueError(f"{where}: unknown dof {sorted(bad)}")
                bone["dof"] = dof
            if key in ("limits",) or (key.startswith("(") and last_key == "limits"):
                text = line[len("limits") :] if key == "limits" else line
                tokens = text.replace("(", " ").replace(")", " ").split()
                lo, hi = _floats(tokens, 2, "limits", where, allow_inf=True)
                bone["limits"].append((float(lo), float(hi)))
                last_key = "limits"
                continue
            last_key = key
        elif section == "hierarchy" and key not in ("begin", "end"):
            for child in tokens[1:]:
                parent[child] = tokens[0]
    if bone is not None:
        raise ValueError("the file ends inside a bone block (truncated?)")
    if not root_order:
        raise ValueError("no ':root' 'order' entry: not an ASF skeleton")
    if not bones:
        raise ValueError("no bones in ':bonedata': not an ASF skeleton, or truncated")
    for child, par in parent.items():
        for b in (child, par):
            if b != "root" and b not in bones:
                raise ValueError(f"ASF hierarchy names an unknown bone {b!r}")
    orphans = [b for b in bones if b not in parent]
    if orphans:
        raise ValueError(f"bones {orphans} are missing from ':hierarchy' (truncated?)")
    return Skeleton(name, units, root_order, bones, parent, root_axis, root_orientation)


def _check_range(
    path: str | Path,
    lines: list[str],
    trial: MocapTrial,
    starts: list[int],
    skeleton: Skeleton,
) -> None:
    """Refuse angles beyond :data:`MAX_ANGLE_DEGREES` and lengths beyond :data:`MAX_LENGTH`,
    naming the first such value's line (``starts``: the line index of each frame's number;
    checked on the whole array at once, as a value at a time would slow the reader down)."""
    degrees = skeleton.units.get("angle", "deg").lower().startswith("deg")
    max_angle, unit = (MAX_ANGLE_DEGREES, "degrees") if degrees else (_MAX_ANGLE_RAD, "radians")
    rotation = np.array([c.split(".")[1] in _ROTATIONS for c in trial.channels])
    bound = np.where(rotation, max_angle, MAX_LENGTH)
    with np.errstate(invalid="ignore"):  # NaN: missing frames, checked elsewhere
        beyond = np.abs(trial.values) > bound
    if not beyond.any():
        return
    row, col = np.argwhere(beyond)[0]
    bone, dof = trial.channels[col].split(".")
    # the frame's bone lines follow the line of its number
    at = next(i for i in range(starts[row] + 1, len(lines)) if lines[i].split()[:1] == [bone])
    where = f"AMC file {path}: line {at + 1} (frame {trial.frame_numbers[row]})"
    value = trial.values[row, col]
    if rotation[col]:
        raise ValueError(
            f"{where}: bone {bone!r} {dof} is {value:g} {unit}; a joint angle beyond "
            f"+-{max_angle:g} {unit} (ten turns) is not a physical value"
        )
    raise ValueError(
        f"{where}: bone {bone!r} {dof} is {value:g} length units; a translation or length "
        f"beyond +-{MAX_LENGTH:g} is not a physical value"
    )


def read_amc(path: str | Path, skeleton: Skeleton, *, gaps: str = "error") -> MocapTrial:
    """Parse an AMC motion file against its skeleton.

    Every frame must give one line for the root and for every bone with degrees of freedom in
    the skeleton (bones without any have no line); nothing is carried over from another frame
    or read as zero. Frame numbers must count up by one.

    Args:
        path: the AMC file.
        skeleton: its subject's skeleton (:func:`read_asf`).
        gaps: ``"error"`` (default): frame numbers that skip (``1`` then ``7``) are an error;
            ``"missing"``: the skipped frames become rows of NaN (missing observations, as the
            toolkit's inference takes them), with their numbers in ``frame_numbers``. Repeated or
            decreasing frame numbers are an error either way.

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file and line (and frame): an empty or binary file, a bone
            unknown to the skeleton or given twice in a frame, a wrong number of values, a
            non-number or non-finite value (``nan``, ``inf``), a joint angle beyond
            +-:data:`MAX_ANGLE_DEGREES` or a translation beyond +-:data:`MAX_LENGTH`, data
            before the first frame number, no frames, frame numbers that repeat, decrease or
            (``gaps="error"``) skip, and a frame (or the whole file) without the line of a bone
            that has degrees of freedom in the skeleton (a truncated file, or the wrong
            skeleton); a bad ``gaps``.
    """
    check_choice(gaps, "gaps", ("error", "missing"))
    lines = text_lines(path, "AMC")
    channels = skeleton.channels()
    index = {c: i for i, c in enumerate(channels)}
    dofs = {"root": skeleton.root_order} | {b.name: b.dof for b in skeleton.bones.values()}
    frames: list[np.ndarray] = []
    numbers: list[int] = []
    starts: list[int] = []  # line index of each frame's number (of the next for skipped ones)
    listed: list[set[str] | None] = []  # bones given in each frame (None: a skipped frame)
    current: np.ndarray | None = None
    given: set[str] = set()  # bones given in the current frame
    for lineno, raw in enumerate(lines, 1):
        line = raw.strip()
        if not line or line.startswith("#") or line.startswith(":"):
            continue
        tokens = line.split()
        if len(tokens) == 1 and tokens[0].isdigit():
            number = int(tokens[0])
            if numbers and number != numbers[-1] + 1:
                _frame_gap(path, lineno, numbers[-1], number, gaps)
                for skipped in range(numbers[-1] + 1, number):  # gaps="missing"
                    frames.append(np.full(len(channels), np.nan))
                    numbers.append(skipped)
                    listed.append(None)
                    starts.append(lineno - 1)
            # NaN until the frame's lines fill it: a bone left out can never pass as zero
            current, given = np.full(len(channels), np.nan), set()
            frames.append(current)
            numbers.append(number)
            listed.append(given)
            starts.append(lineno - 1)
            continue
        where = f"AMC file {path}: line {lineno}"
        if current is None:
            raise ValueError(f"{where}: AMC data before the first frame number")
        where += f" (frame {numbers[-1]})"
        bone = tokens[0]
        if bone not in dofs:
            raise ValueError(f"{where}: bone {bone!r} is not in the skeleton")
        if bone in given:
            raise ValueError(f"{where}: bone {bone!r} is given twice in this frame")
        values = _floats(tokens[1:], len(dofs[bone]), f"bone {bone!r}", where)
        for d, v in zip(dofs[bone], values, strict=True):
            current[index[f"{bone}.{d}"]] = v
        given.add(bone)
    if not frames:
        raise ValueError(f"AMC file {path} contains no frames")
    trial = MocapTrial(np.stack(frames), channels, np.array(numbers))
    _check_range(path, lines, trial, starts, skeleton)
    _check_complete(path, dofs, numbers, listed)
    return trial


def _frame_gap(path: str | Path, lineno: int, previous: int, number: int, gaps: str) -> None:
    """Refuse frame ``number`` after ``previous`` unless it skips frames and gaps are allowed."""
    where = f"AMC file {path}: line {lineno}"
    if number <= previous:
        what = "repeated" if number == previous else "decreasing"
        raise ValueError(
            f"{where}: frame number {number} follows frame {previous} (a {what} frame number); "
            "frame numbers must count up by one"
        )
    if number - previous - 1 > _MAX_SKIPPED:  # not a gap but a corrupted number
        raise ValueError(
            f"{where}: frame {number} follows frame {previous}: a jump of more than "
            f"{_MAX_SKIPPED} frames is not a gap in one recording"
        )
    if gaps == "error":
        skipped = (
            f"frame {previous + 1} is"
            if number == previous + 2
            else f"frames {previous + 1}-{number - 1} are"
        )
        raise ValueError(
            f"{where}: frame {number} follows frame {previous}, so {skipped} missing; pass "
            "gaps='missing' to read them as missing (NaN) frames"
        )


def _check_complete(
    path: str | Path,
    dofs: dict[str, tuple[str, ...]],
    numbers: list[int],
    listed: list[set[str] | None],
) -> None:
    """Every frame read (not a skipped one) must give every bone with degrees of freedom."""
    needed = {bone for bone, d in dofs.items() if d}
    never = needed - set().union(*(b for b in listed if b is not None))
    if never:
        raise ValueError(
            f"AMC file {path}: bones {sorted(never)} of the skeleton have no line in any frame "
            f"(frames {numbers[0]}-{numbers[-1]}); every frame must give every bone with "
            "degrees of freedom (is this the subject's skeleton?)"
        )
    for number, bones in zip(numbers, listed, strict=True):
        missing = set() if bones is None else needed - bones
        if missing:
            raise ValueError(
                f"AMC file {path}: frame {number} lacks bones {sorted(missing)} of the skeleton; "
                "every frame must give every bone with degrees of freedom (truncated file?)"
            )


def load_mocap(
    asf: str | Path,
    amc: str | Path,
    *,
    channels: list[str] | None = None,
    downsample: int = 1,
    normalize: bool | tuple[np.ndarray, np.ndarray] = True,
    dtype: torch.dtype = torch.float64,
    gaps: str = "error",
) -> tuple[torch.Tensor, list[str], tuple[np.ndarray, np.ndarray]]:
    """Load a CMU trial as an observation matrix ``[T, Dz]``.

    Args:
        asf: skeleton file; amc: motion file.
        channels: channels to keep: ``"bone.dof"`` names or whole bone names (all its dofs);
            default all channels that move in the trial (constant channels carry no signal).
        downsample: keep every ``downsample``-th frame (>= 1).
        normalize: ``True``: subtract the per-channel mean and divide by the standard deviation
            of this trial; a ``(mean, std)`` pair: use those (e.g. of the training trials);
            ``False``: raw values.
        dtype: tensor dtype.
        gaps: frames missing from the AMC file (frame numbers that skip): ``"error"`` or
            ``"missing"`` (rows of NaN, left out of the statistics), as in :func:`read_amc`.

    Returns:
        ``z [T, Dz]``, the channel names, and the ``(mean, std)`` used (zeros/ones if none).

    Raises:
        FileNotFoundError, ValueError: unreadable files (see :func:`read_asf`, :func:`read_amc`),
            an unknown channel, no channel that moves, a bad ``downsample``, or ``normalize``
            statistics of the wrong shape, not finite, or with ``std <= 0``.
    """
    if isinstance(downsample, bool) or not isinstance(downsample, int) or downsample < 1:
        raise ValueError(f"downsample must be an int >= 1, got {downsample!r}")
    trial = read_amc(amc, read_asf(asf), gaps=gaps)
    values = trial.values[::downsample]
    if channels is None:
        moves = np.nanmax(trial.values, 0) - np.nanmin(trial.values, 0) > 0  # NaN: missing rows
        keep = np.flatnonzero(moves).tolist()
    else:
        keep = []
        for c in channels:
            hits = [i for i, n in enumerate(trial.channels) if n == c or n.split(".")[0] == c]
            if not hits:
                raise ValueError(f"unknown channel {c!r}; available: {trial.channels}")
            keep += hits
    if not keep:
        raise ValueError("no channel selected (all channels are constant in this trial)")
    values = values[:, keep]
    names = [trial.channels[i] for i in keep]
    if normalize is True:
        # NaN-aware only where frames are missing, so that complete files load as before
        if np.isnan(values).any():
            mean, std = np.nanmean(values, 0), np.nanstd(values, 0)
        else:
            mean, std = values.mean(0), values.std(0)
        std = np.where(std > 0, std, 1.0)
    elif normalize is False:
        mean, std = np.zeros(len(keep)), np.ones(len(keep))
    else:
        mean, std = (np.asarray(a, dtype=float) for a in normalize)
        if mean.shape != (len(keep),) or std.shape != (len(keep),) or not np.all(std > 0):
            raise ValueError(f"normalize must be (mean, std) of shape [{len(keep)}] with std > 0")
        if not (np.isfinite(mean).all() and np.isfinite(std).all()):
            raise ValueError("normalize must be finite (mean, std) statistics")
    return torch.as_tensor((values - mean) / std, dtype=dtype), names, (mean, std)
