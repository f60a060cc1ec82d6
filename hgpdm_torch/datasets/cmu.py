"""The thesis's CMU motion-capture protocols (Sec. 2.4.1) as data, and a loader for any trials.

- :class:`Protocol`: named training and test trials with a label per trial (the subject, or the
  walking style) and the thesis's down-sampling of the 120 frames/s capture.
- :data:`PROTOCOLS`: ``walkers`` (Tables 2.1-2.2), ``weird-walking`` (Tables 2.3-2.4) and
  ``four-walkers`` (Table 2.5, gap recovery).
- :func:`load_trials` / :func:`load_protocol`: CMU ASF/AMC files (CRLF or LF) of any subjects,
  each trial read with its own subject's skeleton ``{subject}.asf``, turned into
  :func:`~hgpdm_torch.datasets.walkers.motion_features`. Trials whose files are absent are listed
  in :attr:`MotionTrials.missing` (or raise, with ``require_all=True``), never silently dropped.

Trial names are CMU's ``"SS_TT"`` (subject, trial number), files ``SS_TT.amc`` and ``SS.asf``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..validation import check_choice
from .mocap import MocapTrial, Skeleton, read_amc, read_asf
from .walkers import motion_features

__all__ = ["PROTOCOLS", "MotionTrials", "Protocol", "load_protocol", "load_trials"]

#: Frame rate of the CMU capture.
CMU_FPS = 120.0


@dataclass
class MotionTrials:
    """Feature sequences of labelled CMU trials.

    Attributes:
        sequences: J trials ``[T_j, F]`` (float64) of :func:`motion_features` (with rows of NaN
            where frames are missing, only if read with ``gaps="missing"``).
        labels: ``[J]`` (long) index of each trial's label in ``label_names``.
        label_names: the labels (subjects ``"07"``, or style names), in code order.
        trials: CMU trial names, e.g. ``"07_01"``.
        features: the ``F`` feature names.
        fps: the common frame rate.
        missing: requested trials whose files were not found (not in ``sequences``).
    """

    sequences: list[torch.Tensor]
    labels: torch.Tensor
    label_names: tuple[str, ...]
    trials: list[str]
    features: list[str]
    fps: float
    missing: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.sequences)


@dataclass(frozen=True)
class Protocol:
    """One of the thesis's CMU protocols.

    Attributes:
        name: e.g. ``"walkers"``.
        label_kind: what the label is (``"subject"`` or ``"style"``).
        label_names: the labels in code order.
        train: ``(trial, label)`` pairs of the training trials.
        test: ``(trial, label)`` pairs of the test trials.
        downsample: keep every ``downsample``-th frame of the 120 frames/s capture.
        table: the thesis's table(s) it reproduces.
    """

    name: str
    label_kind: str
    label_names: tuple[str, ...]
    train: tuple[tuple[str, str], ...]
    test: tuple[tuple[str, str], ...]
    downsample: int
    table: str

    @property
    def fps(self) -> float:
        """The protocol's frame rate (``120 / downsample``)."""
        return CMU_FPS / self.downsample

    def trials(self, split: str) -> tuple[tuple[str, str], ...]:
        """The ``(trial, label)`` pairs of ``split`` (``"train"`` or ``"test"``)."""
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        return self.train if split == "train" else self.test


def _by_subject(spec: dict[str, Sequence[int]]) -> tuple[tuple[str, str], ...]:
    return tuple((f"{s}_{t:02d}", s) for s, trials in spec.items() for t in trials)


_STYLES = {
    "arms out": ((1, 2, 3, 4, 5), (6, 7, 8, 9, 10, 11, 12)),
    "fast": ((17, 18, 19), (20, 21, 22)),
    "hopping on the left foot": ((23, 24, 25), (26, 27, 28)),
    "slow": ((45, 46, 47), (48, 49, 50)),
}

#: The thesis's three protocols (Sec. 2.4.1), by name.
PROTOCOLS: dict[str, Protocol] = {
    "walkers": Protocol(
        name="walkers",
        label_kind="subject",
        label_names=("07", "08", "16", "35"),
        train=_by_subject({"07": (1, 2, 3), "08": (1, 2, 3), "16": (15, 16), "35": (1, 2, 3)}),
        test=_by_subject(
            {"07": (6, 7, 8, 9, 10), "08": (8, 9), "16": (22,), "35": tuple(range(4, 11))}
        ),
        downsample=10,
        table="Tables 2.1-2.2",
    ),
    "weird-walking": Protocol(
        name="weird-walking",
        label_kind="style",
        label_names=tuple(_STYLES),
        train=tuple((f"132_{t:02d}", s) for s, (tr, _) in _STYLES.items() for t in tr),
        test=tuple((f"132_{t:02d}", s) for s, (_, te) in _STYLES.items() for t in te),
        downsample=10,
        table="Tables 2.3-2.4",
    ),
    "four-walkers": Protocol(
        name="four-walkers",
        label_kind="subject",
        label_names=("35", "10", "12", "16"),
        train=_by_subject({"35": (2,), "10": (4,), "12": (1,), "16": (5,)}),
        test=_by_subject({"35": (3,), "12": (2, 3), "16": (21,)}),
        downsample=4,
        table="Table 2.5",
    ),
}


def _features(
    motion: MocapTrial, skeleton: Skeleton, downsample: int
) -> tuple[np.ndarray, list[str]]:
    """:func:`motion_features` of a trial whose missing frames (NaN rows) become NaN rows.

    A feature row describes a resampled frame from it and the one before, so it is missing when
    either of the two is.
    """
    values = motion.values
    missing = np.isnan(values).all(1)
    if not missing.any():
        return motion_features(values, motion.channels, skeleton, CMU_FPS, CMU_FPS / downsample)
    # motion_features takes finite values: hold the last frame read through a gap (the first
    # frame is always read), then blank every row that a missing frame enters
    last = np.maximum.accumulate(np.where(missing, 0, np.arange(len(values))))
    features, names = motion_features(
        values[last], motion.channels, skeleton, CMU_FPS, CMU_FPS / downsample
    )
    gone = missing[::downsample]
    features[gone[1:] | gone[:-1]] = np.nan
    return features, names


def _find(name: str, folders: Sequence[Path]) -> Path | None:
    for folder in folders:
        if (folder / name).is_file():
            return folder / name
    return None


def load_trials(
    trials: Sequence[tuple[str, str]],
    folders: str | Path | Sequence[str | Path],
    *,
    downsample: int,
    label_names: Sequence[str] | None = None,
    require_all: bool = False,
    gaps: str = "error",
) -> MotionTrials:
    """Read labelled CMU trials from ASF/AMC files.

    Each trial ``SS_TT`` needs ``SS_TT.amc`` and its subject's ``SS.asf``, looked up in
    ``folders`` in order (so a test folder may rely on the training folder's skeletons). Every
    subject's own skeleton is used; all trials must give the same feature channels.

    Args:
        trials: ``(trial, label)`` pairs, e.g. ``[("07_01", "07"), ...]``.
        folders: folder(s) holding the files.
        downsample: keep every ``downsample``-th frame of the 120 frames/s capture (>= 1).
        label_names: the labels in code order (default: the labels of ``trials`` in order of
            first appearance); every label must be among them.
        require_all: raise if a trial's files are absent instead of listing it in ``missing``.
        gaps: frames missing from an AMC file (frame numbers that skip): ``"error"`` (default)
            or ``"missing"``: the feature rows that a missing frame enters (its own and the
            next one's, as features difference consecutive frames) are rows of NaN, missing
            observations to the toolkit's inference (see :func:`~.mocap.read_amc`).

    Returns:
        :class:`MotionTrials` of the trials found, in the order given.

    Raises:
        FileNotFoundError: a folder does not exist, or (``require_all``) a trial is missing.
        ValueError: a bad trial name, label, ``downsample`` or ``gaps``, trials with different
            channels, or a malformed file (:func:`~.mocap.read_asf`, :func:`~.mocap.read_amc`:
            a bone missing from a frame, an angle beyond the physical range, frame numbers that
            do not count up by one, ...), naming the file.
    """
    if isinstance(folders, str | Path):
        folders = [folders]
    paths = [Path(f) for f in folders]
    for folder in paths:
        if not folder.is_dir():
            raise FileNotFoundError(f"CMU data folder not found: {folder}")
    if isinstance(downsample, bool) or not isinstance(downsample, int) or downsample < 1:
        raise ValueError(f"downsample must be a positive int, got {downsample!r}")
    check_choice(gaps, "gaps", ("error", "missing"))
    pairs = [(str(t), str(lab)) for t, lab in trials]
    names = (
        tuple(label_names) if label_names is not None else tuple(dict.fromkeys(l for _, l in pairs))
    )
    for trial, label in pairs:
        if trial.count("_") != 1 or not all(p.isdigit() for p in trial.split("_")):
            raise ValueError(f"trials: expected CMU names like '07_01', got {trial!r}")
        if label not in names:
            raise ValueError(f"trials: label {label!r} of {trial} is not in {names}")
    skeletons: dict[str, Skeleton] = {}
    sequences, found, labels, missing = [], [], [], []
    features: list[str] | None = None
    for trial, label in pairs:
        subject = trial.split("_")[0]
        amc, asf = _find(f"{trial}.amc", paths), _find(f"{subject}.asf", paths)
        if amc is None or asf is None:
            what = f"{trial}.amc" if amc is None else f"{subject}.asf"
            if require_all:
                raise FileNotFoundError(f"{what} not found in {[str(p) for p in paths]}")
            missing.append(trial)
            continue
        if subject not in skeletons:
            skeletons[subject] = read_asf(asf)
        motion = read_amc(amc, skeletons[subject], gaps=gaps)
        values, names_f = _features(motion, skeletons[subject], downsample)
        if features is not None and names_f != features:
            raise ValueError(
                f"{trial}: its skeleton gives other channels than the trials before it: "
                f"{sorted(set(names_f) ^ set(features))}"
            )
        features = names_f
        sequences.append(torch.as_tensor(values, dtype=torch.float64))
        found.append(trial)
        labels.append(names.index(label))
    return MotionTrials(
        sequences=sequences,
        labels=torch.tensor(labels, dtype=torch.long),
        label_names=names,
        trials=found,
        features=features or [],
        fps=CMU_FPS / downsample,
        missing=missing,
    )


def load_protocol(
    protocol: str | Protocol,
    split: str = "train",
    folder: str | Path | Sequence[str | Path] = "../shared/data/cmu",
    *,
    require_all: bool = False,
    gaps: str = "error",
) -> MotionTrials:
    """The ``split`` trials of a protocol (:data:`PROTOCOLS` name or a :class:`Protocol`), at
    its frame rate, labelled with its ``label_names``; absent trials listed in ``missing``.

    ``folder`` may list several folders (e.g. a test folder, then the training folder for the
    skeletons). ``require_all`` and ``gaps`` are those of :func:`load_trials`, which also says
    what is refused.
    """
    if isinstance(protocol, str):
        if protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {sorted(PROTOCOLS)}, got {protocol!r}")
        protocol = PROTOCOLS[protocol]
    return load_trials(
        protocol.trials(split),
        folder,
        downsample=protocol.downsample,
        label_names=protocol.label_names,
        require_all=require_all,
        gaps=gaps,
    )
