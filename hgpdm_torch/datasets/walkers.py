"""Preprocessing of CMU walks (thesis Sec. 2.4.1) as in Taylor et al. (2007, 2011); the trials
and protocols themselves are in :mod:`hgpdm_torch.datasets.cmu`.

- :func:`motion_features`: one trial's raw ASF/AMC channels ``[T, C]`` -> features ``[T', F]``:
  root velocity in the heading frame, root height, yaw rate, pitch and roll, and joint angles in
  radians wrapped to ``[-pi, pi)``, after resampling to a common frame rate.
- :class:`Standardizer`: drops the channels that are constant in the training trials and
  standardises the rest with training statistics; maps back to the full channel layout.
- :func:`frame_features`: each frame alone, beside its change from the previous frame, or beside
  the previous frame: what a model observes to tell apart phases of a movement that pass through
  the same pose.
- :func:`find_trials` / :class:`FoundTrials`: which of a protocol's trials a folder holds, per
  label, from the file names alone, so that a run says what it found (and stops with
  :class:`MissingTrialsError` when it lacks what it needs) before any work
  (:func:`protocol_trials`: what a forecasting run needs);
  :func:`loto_folds` / :func:`spread_folds`: leave-one-trial-out folds over the trials.

Conventions of the CMU (VICON) data, checked on the files: ``y`` is up; the root's ``rx ry rz``
are rotations about the fixed global axes in the sequence of the ASF ``order`` line (``RX RY RZ``:
``R = Rz(rz) Ry(ry) Rx(rx)`` acting on column vectors); in the root's own frame the body faces
``+z`` and its left is ``+x`` (the left hip lies at ``+x``, and the walks advance along the
direction ``R e_z``). Lengths are in the ASF's units: CMU uses ``length 0.45``, i.e.
``0.0254 / 0.45`` m per unit (root height ~17 units ~ 0.96 m).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..validation import as_tensor
from .mocap import Skeleton

if TYPE_CHECKING:  # cmu imports this module
    from .cmu import MotionTrials, Protocol

__all__ = [
    "FRAME_FEATURES",
    "FoundTrials",
    "MissingTrialsError",
    "Standardizer",
    "find_trials",
    "frame_features",
    "loto_folds",
    "motion_features",
    "protocol_trials",
    "spread_folds",
]

ROOT_FEATURES = (
    "root.vx_heading",
    "root.vz_heading",
    "root.ty",
    "root.yaw_rate",
    "root.pitch",
    "root.roll",
)
_ROOT_CHANNELS = ("tx", "ty", "tz", "rx", "ry", "rz")
_ROTATIONS = ("rx", "ry", "rz")


def wrap_angles(angle: np.ndarray) -> np.ndarray:
    """Angles in radians wrapped to ``[-pi, pi)``."""
    out = np.mod(angle + np.pi, 2 * np.pi) - np.pi
    return np.where(out >= np.pi, out - 2 * np.pi, out)  # mod may round up to 2 pi


def _axis_rotation(axis: str, angle: np.ndarray) -> np.ndarray:
    """Right-handed rotations about the coordinate ``axis`` (``"x"``, ``"y"``, ``"z"``) by
    ``angle [T]`` radians: ``[T, 3, 3]``, acting on column vectors."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.zeros((len(angle), 3, 3))
    r[:, "xyz".index(axis), "xyz".index(axis)] = 1.0
    r[:, i, i], r[:, i, j], r[:, j, i], r[:, j, j] = c, -s, s, c
    return r


def _fixed_axis_rotation(angles: dict[str, np.ndarray], sequence: Sequence[str]) -> np.ndarray:
    """Rotations about the fixed axes in ``sequence`` (first applied first): for ``x, y, z``,
    ``R = Rz Ry Rx`` ``[T, 3, 3]``."""
    rot = np.broadcast_to(np.eye(3), (len(angles[sequence[0]]), 3, 3))
    for axis in sequence:
        rot = _axis_rotation(axis, angles[axis]) @ rot
    return rot


def _heading_pitch_roll(rot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split root rotations ``[T, 3, 3]`` as ``R = Ry(yaw) Rx(pitch) Rz(roll)``.

    ``yaw`` is the heading of the forward axis ``R e_z`` on the ground (``atan2(x, z)``);
    ``pitch > 0`` tilts the forward axis down, ``roll > 0`` lifts the left side (``+x``).
    Undefined when the forward axis is vertical (``|pitch| = pi/2``).
    """
    yaw = np.arctan2(rot[:, 0, 2], rot[:, 2, 2])
    rest = _axis_rotation("y", -yaw) @ rot  # Rx(pitch) Rz(roll)
    pitch = np.arctan2(-rest[:, 1, 2], rest[:, 2, 2])
    tilt = _axis_rotation("x", -pitch) @ rest  # Rz(roll)
    roll = np.arctan2(tilt[:, 1, 0], tilt[:, 0, 0])
    return yaw, pitch, roll


def _is_real(value: object) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _stride(fps: float, target_fps: float | None) -> int:
    for name, value in (("fps", fps), ("target_fps", target_fps)):
        if value is not None and not (_is_real(value) and 0 < value < math.inf):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    if target_fps is None:
        return 1
    ratio = fps / target_fps
    stride = round(ratio)
    if stride < 1 or abs(ratio - stride) > 1e-9 * ratio:
        raise ValueError(
            f"target_fps must divide fps = {fps} by an integer (frames are subsampled, not "
            f"interpolated), got target_fps = {target_fps}"
        )
    return stride


def motion_features(
    values: Any,
    channels: Sequence[str],
    skeleton: Skeleton,
    fps: float,
    target_fps: float | None = None,
) -> tuple[np.ndarray, list[str]]:
    """Taylor et al.'s features of one trial.

    1. Resampling: every ``fps / target_fps``-th frame from the first, which must be an integer
       stride (no interpolation: the CMU rates 120 and 30 frames/s reach 15 by strides 8 and 2).
    2. Root: the ground-plane translation ``(tx, tz)`` becomes the displacement between
       consecutive resampled frames, expressed in the heading frame of the earlier one
       (``root.vz_heading``: forward, ``root.vx_heading``: towards the body's left); the height
       ``root.ty`` is kept; the orientation ``R`` (from ``rx ry rz`` in the sequence of the ASF
       ``order`` line, about fixed axes) is split as ``R = Ry(yaw) Rx(pitch) Rz(roll)``: the
       heading ``yaw`` enters as its wrapped change between frames (``root.yaw_rate``, radians
       per resampled frame, > 0 turning left), ``root.pitch`` (> 0 leaning forward) and
       ``root.roll`` (> 0 left side up) are kept as angles, relative to the heading frame.
    3. Every other rotation channel: radians (from the ASF ``units`` angle, degrees by default),
       wrapped to ``[-pi, pi)``; other channels (bone ``tx``/``l`` dofs) are kept as they are.

    Velocities are backward differences, so row ``i`` describes resampled frame ``i + 1`` from
    it and the frame before: the output has one frame fewer than the resampled input, and every
    row depends only on the present and past. Constant channels are kept (drop them with
    training statistics, see :class:`Standardizer`). Lengths stay in the ASF's units.

    Args:
        values: ``[T, C]`` raw channel values of a trial, as :func:`~.mocap.read_amc` gives them.
        channels: the ``C`` channel names ``"bone.dof"``; must include the six root channels
            ``root.tx ty tz rx ry rz``, and every name must be a channel of ``skeleton``.
        skeleton: the trial's ASF skeleton (root ``order``, angle units).
        fps: frame rate of ``values``.
        target_fps: frame rate of the output; ``None`` keeps ``fps``.

    Returns:
        ``features [T', F]`` with ``T' = ceil(T / stride) - 1`` and ``F = C``, and their names:
        ``ROOT_FEATURES`` (``root.vx_heading``, ``root.vz_heading``, ``root.ty``,
        ``root.yaw_rate``, ``root.pitch``, ``root.roll``), then the non-root channels in the
        order of ``channels``.

    Raises:
        ValueError: ``values`` not a finite ``[T, C]`` array matching ``channels``, unknown or
            missing channels, a non-zero pre-set root orientation, fewer than two resampled
            frames, or a bad ``fps``/``target_fps``.
    """
    stride = _stride(fps, target_fps)
    x = as_tensor(values, "values", dtype=torch.float64, ndim=2).cpu().numpy()
    channels = list(channels)
    if x.shape[1] != len(channels):
        raise ValueError(
            f"channels must name the {x.shape[1]} columns of values, got {len(channels)} names"
        )
    known = set(skeleton.channels())
    unknown = [c for c in channels if c not in known]
    missing = [f"root.{d}" for d in _ROOT_CHANNELS if f"root.{d}" not in channels]
    if unknown or missing or len(set(channels)) != len(channels):
        raise ValueError(
            f"channels must be distinct channels of the skeleton including all six root "
            f"channels; unknown {unknown}, missing {missing}"
        )
    if np.any(np.asarray(skeleton.root_orientation) != 0):
        raise ValueError(
            f"skeleton has a pre-set root orientation {skeleton.root_orientation}: only zero "
            f"(as in CMU/VICON files) is supported"
        )
    x = x[::stride]
    if x.shape[0] < 2:
        raise ValueError(f"values must have at least 2 frames after resampling, got {len(x)}")
    col = {c: i for i, c in enumerate(channels)}
    degrees = skeleton.units.get("angle", "deg").lower().startswith("deg")
    to_rad = math.pi / 180 if degrees else 1.0

    sequence = [d[1] for d in skeleton.root_order if d in _ROTATIONS]
    angles = {d[1]: to_rad * x[:, col[f"root.{d}"]] for d in _ROTATIONS}
    yaw, pitch, roll = _heading_pitch_roll(_fixed_axis_rotation(angles, sequence))
    dx = np.diff(x[:, col["root.tx"]])
    dz = np.diff(x[:, col["root.tz"]])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    columns = [
        c * dx - s * dz,  # towards the body's left, Ry(yaw) e_x
        s * dx + c * dz,  # forward, Ry(yaw) e_z
        x[1:, col["root.ty"]],
        wrap_angles(np.diff(yaw)),
        wrap_angles(pitch[1:]),
        wrap_angles(roll[1:]),
    ]
    names = list(ROOT_FEATURES)
    for name in channels:
        if name.startswith("root."):
            continue
        v = x[1:, col[name]]
        columns.append(wrap_angles(to_rad * v) if name.split(".")[1] in _ROTATIONS else v)
        names.append(name)
    return np.stack(columns, axis=1), names


# ------------------------------------------------------------------------------------------
# Standardisation with training statistics
# ------------------------------------------------------------------------------------------


class Standardizer:
    """Drop the channels that are constant in training, standardise the others.

    A channel counts as constant when its standard deviation over all training frames is at most
    ``rtol * (1 + max |x|)`` (relative to its magnitude, so that rounding noise of a large
    constant value is no signal). Statistics are population ones (``ddof = 0``).

    Args:
        rtol: the relative threshold.

    Attributes (after :meth:`fit`):
        mean_: ``[F]`` training mean of every channel (the value of a constant one).
        scale_: ``[F]`` training standard deviation (1 for constant channels).
        keep_: ``[F]`` bool, the channels that vary in training (``F_kept`` of them).
    """

    def __init__(self, rtol: float = 1e-8) -> None:
        if not (_is_real(rtol) and 0 <= rtol < math.inf):
            raise ValueError(f"rtol must be a finite number >= 0, got {rtol!r}")
        self.rtol = float(rtol)

    def fit(self, sequences: Sequence[Any] | torch.Tensor) -> Standardizer:
        """Training statistics of ``J`` sequences ``[T_j, F]`` (or one array ``[..., F]``).
        Missing values (NaN: a gap of a C3D marker, a frame ``gaps="missing"`` read) are left
        out of each channel's statistics.

        Raises:
            ValueError: no frame, an inf, or a channel missing in every frame.
        """
        if isinstance(sequences, torch.Tensor | np.ndarray):
            x = as_tensor(sequences, "sequences", min_ndim=1, allow_nan=True)
            x = x.reshape(-1, x.shape[-1])
        else:
            if len(sequences) == 0:
                raise ValueError("sequences must be a non-empty list of [T_j, F] arrays")
            parts = [as_tensor(s, f"sequences[{j}]", ndim=2, allow_nan=True)
                     for j, s in enumerate(sequences)]  # fmt: skip
            if any(p.shape[1] != parts[0].shape[1] for p in parts):
                raise ValueError("all sequences must have the same number of channels F")
            x = torch.cat([p.to(parts[0]) for p in parts])
        if x.shape[0] == 0:
            raise ValueError("sequences must contain at least one frame")
        seen = ~x.isnan()
        if empty := torch.nonzero(~seen.any(0)).flatten().tolist():
            raise ValueError(f"channels {empty} are missing (NaN) in every training frame")
        if bool(seen.all()):  # complete data: torch's own reductions, as before gaps existed
            self.mean_, std = x.mean(0), x.std(0, correction=0)
        else:
            self.mean_ = x.nanmean(0)
            std = (x - self.mean_).pow(2).nanmean(0).sqrt()
        self.keep_ = std > self.rtol * (1 + x.nan_to_num(0.0).abs().amax(0))
        self.scale_ = torch.where(self.keep_, std, torch.ones_like(std))
        return self

    def _check(self, z: Any, kept: bool, name: str) -> torch.Tensor:
        if not hasattr(self, "keep_"):
            raise RuntimeError("call fit before transform or inverse_transform")
        width = int(self.keep_.sum()) if kept else self.keep_.numel()
        z = as_tensor(z, name, min_ndim=1, allow_nan=True)  # missing values stay missing
        if z.shape[-1] != width:
            raise ValueError(f"{name} must have {width} channels in its last dim, got {z.shape}")
        return z

    def transform(self, z: Any) -> torch.Tensor:
        """``[..., F]`` -> ``[..., F_kept]``: the varying channels, standardised."""
        z = self._check(z, False, "z")
        keep = self.keep_.to(z.device)
        mean, scale = (a.to(z)[keep] for a in (self.mean_, self.scale_))
        return (z[..., keep] - mean) / scale

    def inverse_transform(self, u: Any) -> torch.Tensor:
        """``[..., F_kept]`` -> ``[..., F]``: original units, constant channels re-inserted at
        their training value."""
        u = self._check(u, True, "u")
        keep = self.keep_.to(u.device)
        mean, scale = self.mean_.to(u), self.scale_.to(u)
        out = mean.expand(*u.shape[:-1], mean.numel()).clone()
        out[..., keep] = u * scale[keep] + mean[keep]
        return out

    def kept(self, names: Sequence[str]) -> list[str]:
        """The names of the kept channels, given the ``F`` names of all of them."""
        if not hasattr(self, "keep_"):
            raise RuntimeError("call fit before kept")
        if len(names) != self.keep_.numel():
            raise ValueError(f"names must list the {self.keep_.numel()} channels, got {len(names)}")
        return [n for n, k in zip(names, self.keep_.tolist(), strict=True) if k]


# ------------------------------------------------------------------------------------------
# Features of consecutive frames
# ------------------------------------------------------------------------------------------

#: the kinds of :func:`frame_features`
FRAME_FEATURES = ("frames", "velocity", "lagged")


def frame_features(z: Any, kind: str) -> torch.Tensor:
    """What a model observes of frames ``z [..., T, D]``.

    - ``"frames"``: the frames themselves, ``[..., T, D]``;
    - ``"velocity"``: each frame beside its change, ``[..., T - 1, 2 D]``, row ``t`` holding
      ``[z_{t+1}, z_{t+1} - z_t]``;
    - ``"lagged"``: each frame beside the previous one, ``[..., T - 1, 2 D]``, row ``t`` holding
      ``[z_{t+1}, z_t]`` (the same information as ``"velocity"``, a different basis: with one
      RBF measurement GP per output and the output scales ``W`` the models differ).

    The thesis's measurement model scales each output (``W``, Sec. 2.2) so that "raw features
    measured in different units, such as positions and velocities" can be modelled together;
    with the change (or the previous frame) beside the pose, a latent state must also say where
    the movement goes (a hop's way up and way down pass through the same poses). The first frame
    has no predecessor and is dropped. A missing (NaN) value spoils its own row and, in the
    second half, the next row.

    Args:
        z: ``[..., T, D]`` frames (``T >= 2`` unless ``kind`` is ``"frames"``).
        kind: one of :data:`FRAME_FEATURES`.

    Returns:
        The features; their first ``D`` channels are the frames (from the second frame on).
    """
    if kind not in FRAME_FEATURES:
        raise ValueError(f"kind must be one of {FRAME_FEATURES}, got {kind!r}")
    z = as_tensor(z, "z", min_ndim=2, allow_nan=True)
    if kind == "frames":
        return z
    if z.shape[-2] < 2:
        raise ValueError(
            f"{kind} features need at least 2 frames (rows) of z, got {tuple(z.shape)}"
        )
    later, earlier = z[..., 1:, :], z[..., :-1, :]
    return torch.cat([later, later - earlier if kind == "velocity" else earlier], dim=-1)


# ------------------------------------------------------------------------------------------
# Which of a protocol's trials are there, and leave-one-trial-out folds over them
# ------------------------------------------------------------------------------------------


class MissingTrialsError(FileNotFoundError, ValueError):
    """A protocol run lacks the trials it needs (both a ``FileNotFoundError``, as the loaders
    raise for absent files, and a ``ValueError``); the message names the folder and the files
    expected there."""


@dataclass(frozen=True)
class FoundTrials:
    """Which of a protocol's trials of one split lie in a folder, by file names alone (nothing
    is read, so a run can say what it found, and stop, before any work).

    A trial ``SS_TT`` is found when ``SS_TT.amc`` is in the folder and its subject's skeleton
    ``SS.asf`` is in the folder or a skeleton folder: exactly the trials that
    :func:`~hgpdm_torch.datasets.cmu.load_trials` would read from ``[folder, *skeletons]``.

    Attributes:
        protocol: the protocol's name, e.g. ``"walkers"``.
        split: ``"training"`` or ``"test"``.
        source: how messages name the folder, e.g. ``"--data ../shared/data/cmu"``.
        label_kind: what a label is (``"subject"`` or ``"style"``).
        label_names: the protocol's labels, in code order.
        found: ``(trial, label)`` pairs found, in the protocol's order.
        missing: ``(trial, label, file)`` of the others, ``file`` the absent one (the trial's
            ``.amc``, or its subject's ``.asf``).
    """

    protocol: str
    split: str
    source: str
    label_kind: str
    label_names: tuple[str, ...]
    found: tuple[tuple[str, str], ...]
    missing: tuple[tuple[str, str, str], ...]

    @property
    def trials(self) -> list[str]:
        """The trials found."""
        return [t for t, _ in self.found]

    @property
    def missing_trials(self) -> list[str]:
        """The protocol's trials of this split that were not found."""
        return [t for t, _, _ in self.missing]

    def describe(self) -> str:
        """One line: per label the trials found and those missing (and the absent skeletons
        of trials whose motion file is there)."""
        parts = []
        for label in self.label_names:
            have = [t for t, lab in self.found if lab == label]
            lack = [(t, absent) for t, lab, absent in self.missing if lab == label]
            if not (have or lack):  # the protocol has no trial of this label in this split
                continue
            text = f"{self.label_kind} {label}: {', '.join(have) or 'none'}"
            if lack:
                asf = [a for _, a in dict.fromkeys(lack) if a.endswith(".asf")]
                why = f": no {', '.join(dict.fromkeys(asf))}" if asf else ""
                text += f" ({', '.join(t for t, _ in lack)} missing{why})"
            parts.append(text)
        return f"{self.split} trials from {self.source}: " + "; ".join(parts)

    def _expected(self, labels: Sequence[str]) -> str:
        """The files of ``labels``, which have no trial found (so all theirs are missing)."""
        trials = [t for t, lab, _ in self.missing if lab in labels]
        subjects = dict.fromkeys(t.split("_")[0] for t in trials)
        files = ", ".join(f"{t}.amc" for t in trials)
        one = "" if len(trials) == 1 else "one of "
        return f"{one}{files} with {', '.join(f'{s}.asf' for s in subjects)}"

    def require(self, need: str) -> None:
        """Stop unless the trials found meet ``need``: ``"any"`` (at least one trial),
        ``"every label"`` (a trial of every label) or ``"all"`` (every trial).

        Raises:
            MissingTrialsError: naming the folder, the labels without a trial and the files
                expected for them (or the missing trials, for ``"all"``).
            ValueError: an unknown ``need``.
        """
        if need not in ("any", "every label", "all"):
            raise ValueError(f"need must be 'any', 'every label' or 'all', got {need!r}")
        if need == "all" and self.missing:
            lack = ", ".join(dict.fromkeys(absent for _, _, absent in self.missing))
            raise MissingTrialsError(
                f"{self.source}: the {self.protocol} {self.split} trials must all be there; "
                f"absent: {lack}"
            )
        if not self.found:
            raise MissingTrialsError(
                f"{self.source}: no {self.protocol} {self.split} trial (expected "
                f"{self._expected(self.label_names)})"
            )
        have = {lab for _, lab in self.found}
        empty = [lab for lab in self.label_names if lab not in have]
        if need == "every label" and empty:
            each = "; ".join(
                f"{self.label_kind} {lab} (expected {self._expected([lab])})" for lab in empty
            )
            raise MissingTrialsError(
                f"{self.source}: no {self.split} trial for {each}; the {self.protocol} protocol "
                f"needs one of every {self.label_kind}"
            )


def find_trials(
    protocol: Protocol,
    split: str,
    folder: str | Path,
    *,
    skeletons: Sequence[str | Path] = (),
    source: str | None = None,
) -> FoundTrials:
    """Which of ``protocol``'s ``split`` trials are in ``folder`` (see :class:`FoundTrials`).

    Args:
        protocol: a :class:`~hgpdm_torch.datasets.cmu.Protocol`.
        split: ``"train"`` or ``"test"``.
        folder: where the trials' ``.amc`` files must be.
        skeletons: further folders for the subjects' ``.asf`` skeletons (after ``folder``).
        source: how messages name ``folder`` (default: its path).

    Raises:
        FileNotFoundError: ``folder`` or a skeleton folder is not a folder.
    """
    folders = [Path(folder), *map(Path, skeletons)]
    for f in folders:
        if not f.is_dir():
            raise FileNotFoundError(f"CMU data folder not found: {f}")
    found, missing = [], []
    for trial, label in protocol.trials(split):
        asf = f"{trial.split('_')[0]}.asf"
        if not (folders[0] / f"{trial}.amc").is_file():
            missing.append((trial, label, f"{trial}.amc"))
        elif not any((f / asf).is_file() for f in folders):
            missing.append((trial, label, asf))
        else:
            found.append((trial, label))
    return FoundTrials(
        protocol.name,
        "training" if split == "train" else "test",
        str(folder) if source is None else source,
        protocol.label_kind,
        protocol.label_names,
        tuple(found),
        tuple(missing),
    )


def protocol_trials(
    spec: Protocol,
    folder: str | Path,
    test_folder: str | Path | None = None,
    names: tuple[str, str] = ("folder", "test_folder"),
) -> tuple[FoundTrials, FoundTrials | None]:
    """Which of ``spec``'s training trials ``folder`` holds and, if ``test_folder`` is given,
    which test trials it holds (their skeletons may lie in ``folder``; their motions are never
    taken from it), checked against what a forecasting run
    (:func:`~hgpdm_torch.experiments.walkers.walkers`) needs: a training trial of every label;
    with ``test_folder``, a test trial there and two training trials; without, for
    leave-one-trial-out CV, a label with two training trials and three trials in all (every
    fit's baselines choose their settings by cross-validation over at least two trials).

    Args:
        spec: the protocol (a :class:`~hgpdm_torch.datasets.cmu.Protocol`).
        folder: the training trials' folder.
        test_folder: the test trials' folder; ``None``: leave-one-trial-out CV.
        names: how messages name the two folders (``("--data", "--test-data")`` on the
            command line).

    Returns:
        The training trials found and the test trials found (``None`` without ``test_folder``).

    Raises:
        MissingTrialsError: a label without a training trial, no test trial in ``test_folder``,
            or (CV) no label with two training trials to hold one out.
        FileNotFoundError: a folder that does not exist.
    """
    train = find_trials(spec, "train", folder, source=f"{names[0]} {folder}")
    train.require("every label")
    labels = [lab for _, lab in train.found]
    if test_folder is None and all(labels.count(lab) < 2 for lab in labels):
        raise MissingTrialsError(
            f"{train.source}: leave-one-trial-out CV needs a {spec.label_kind} with two training "
            f"trials (one held out, one to train), found one each: {train.trials}"
        )
    # every fit's baselines choose their settings by cross-validation over >= 2 training trials
    need = 3 if test_folder is None else 2
    if len(train.found) < need:
        raise MissingTrialsError(
            f"{train.source}: found the training trials {train.trials} only; "
            f"{'leave-one-trial-out CV' if need == 3 else 'scoring test trials'} needs at least "
            f"{need} (ridge AR and the GRU choose their settings by cross-validation by trial)"
        )
    if test_folder is None:
        return train, None
    source = f"{names[1]} {test_folder}"
    test = find_trials(spec, "test", test_folder, skeletons=[folder], source=source)
    test.require("any")
    return train, test


def loto_folds(labels: Any) -> tuple[list[tuple[list[int], list[int]]], list[int]]:
    """Leave-one-trial-out folds over the trials whose label has at least one other trial.

    Args:
        labels: ``[J]`` label code per trial.

    Returns:
        ``(train, [held-out trial])`` per testable trial, in trial order, and the trials that
        cannot be held out (their label's only trial; they always train).
    """
    codes = np.asarray(labels).reshape(-1)
    folds, untestable = [], []
    for j, code in enumerate(codes.tolist()):
        if int((codes == code).sum()) < 2:
            untestable.append(j)
            continue
        folds.append(([i for i in range(len(codes)) if i != j], [j]))
    return folds, untestable


def spread_folds(
    folds: list[tuple[list[int], list[int]]], data: MotionTrials, max_folds: int | None
) -> list[tuple[list[int], list[int]]]:
    """At most ``max_folds`` of :func:`loto_folds`' folds (all for ``None``), taking the labels'
    held-out trials in turn, in the trials' order."""
    if max_folds is None or max_folds >= len(folds):
        return folds
    by_label: dict[int, list[tuple[list[int], list[int]]]] = {}
    for fold in folds:
        by_label.setdefault(int(data.labels[fold[1][0]]), []).append(fold)
    order = [f for i in range(len(folds)) for group in by_label.values() for f in group[i : i + 1]]
    return sorted(order[:max_folds], key=lambda f: f[1][0])
