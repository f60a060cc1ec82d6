"""Table-tennis trials and the enumerated reward table of thesis Sec. 4.3.2.

A trial is one stroke of the simulated opponent (:mod:`.opponent`): the observations the robot sees
before the opponent's hit, the true target and the ball leaving the opponent's racket. Evaluating a
trial runs the SAPIEN scene with one of the robot's movements initiated at one time; the reward is
+1 for a legal return and -1 otherwise, as in the thesis. :func:`reward_table` enumerates every
(trial, movement, start time) combination on an executor of :mod:`hgpdm_torch.parallel` (this
process, local processes or a Ray cluster) and caches every cell on disk, each file with a
checksum of its rewards and of the simulation they came from.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ...parallel import Executor, get_executor
from ...progress import tqdm
from . import ball as B
from . import geometry as geo
from .opponent import OpponentConfig, sample_strokes
from .scene import SceneConfig, TableTennisScene
from .strokes import MOVEMENTS, StrokeConfig, StrokeOutcome, StrokePlanner, execute_stroke

__all__ = [
    "DEFAULT_START_TIMES",
    "Trial",
    "Trials",
    "check_cache_dir",
    "default_cache_dir",
    "evaluate",
    "hitting_regions",
    "make_trials",
    "reward_table",
]

DEFAULT_START_TIMES = (-0.32, -0.24, -0.16, -0.08, 0.0)
"""Movement start times relative to the opponent's hit [s], one per 80 ms observation."""


@dataclass(frozen=True)
class Trial:
    """One opponent stroke as the robot meets it.

    Attributes:
        obs: ``[T, Dz]`` observations before the hit; ``obs_times``: ``[T]`` relative to the hit.
        target: ``x`` where the ball crosses the robot's hitting plane (m).
        hit_time: time of the opponent's hit after the robot's previous hit (s).
        ball_after_hit: unbatched :class:`.ball.BallState` leaving the opponent's racket.
    """

    obs: torch.Tensor
    obs_times: torch.Tensor
    target: float
    hit_time: float
    ball_after_hit: B.BallState


@dataclass(frozen=True)
class Trials:
    """A batch of ``n`` trials. Shapes: ``obs [n, T, Dz]``, ``targets [n]``, ``hit_times [n]``,
    ``ball_after_hit`` fields ``[n, 3]``, ``obs_times [T]``."""

    obs: torch.Tensor
    obs_times: torch.Tensor
    targets: torch.Tensor
    hit_times: torch.Tensor
    ball_after_hit: B.BallState

    def __len__(self) -> int:
        return int(self.targets.shape[0])

    def __getitem__(self, i: int) -> Trial:
        return Trial(
            self.obs[i],
            self.obs_times,
            float(self.targets[i]),
            float(self.hit_times[i]),
            B.BallState(*(f[i] for f in self.ball_after_hit)),
        )

    def fingerprints(self) -> list[str]:
        """``n`` hashes, one per trial, of the ball that defines it (values and dtype): the data
        part of the reward cache's key. Equal balls have equal fingerprints."""
        fields = [f.detach().cpu().numpy() for f in self.ball_after_hit]
        return [_ball_key(*(f[i] for f in fields)) for i in range(len(self))]


def _ball_key(*arrays: np.ndarray) -> str:
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(a.dtype.str.encode())
        h.update(a.tobytes())
    return h.hexdigest()[:24]


def make_trials(
    n: int,
    seed: int,
    *,
    targets: object | None = None,
    config: OpponentConfig | None = None,
    progress: bool = False,
) -> Trials:
    """Sample ``n`` trials from the simulated opponent with a seeded generator.

    ``targets`` ``[n]`` fixes the intended targets (default: uniform over the hitting plane); see
    :func:`.opponent.sample_strokes`.
    """
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise TypeError(f"seed must be an int, got {type(seed).__name__}")
    gen = torch.Generator().manual_seed(seed)
    s = sample_strokes(n, config=config, targets=targets, generator=gen, progress=progress)
    return Trials(s.obs, s.obs_times, s.targets, s.hit_time, s.ball_after_hit)


class _Simulator:
    """One scene and planner, reused across evaluations (built once per process)."""

    def __init__(self, scene_config: SceneConfig | None, stroke_config: StrokeConfig | None):
        self.planner = StrokePlanner(config=stroke_config)
        self.scene = TableTennisScene(scene_config, wam=self.planner.wam)

    def run(self, ball: B.BallState, action: str, start_time: float) -> StrokeOutcome:
        return execute_stroke(self.scene, self.planner, ball, action, start_time)


_SIMULATORS: dict[tuple, _Simulator] = {}


def _simulator(scene_config: SceneConfig | None, stroke_config: StrokeConfig | None) -> _Simulator:
    key = (repr(scene_config), repr(stroke_config), torch.get_default_dtype())
    if key not in _SIMULATORS:
        _SIMULATORS[key] = _Simulator(scene_config, stroke_config)
    return _SIMULATORS[key]


def evaluate(
    trial: Trial,
    action: str,
    start_time: float,
    *,
    scene_config: SceneConfig | None = None,
    stroke_config: StrokeConfig | None = None,
) -> StrokeOutcome:
    """Run the SAPIEN scene for one trial with ``action`` initiated at ``start_time``.

    Args:
        trial: the opponent's stroke.
        action: ``"forehand"``, ``"middle"`` or ``"backhand"``.
        start_time: movement initiation relative to the opponent's hit [s] (negative: before).
        scene_config: scene settings (defaults when ``None``).
        stroke_config: stroke settings (defaults when ``None``).

    Raises:
        ValueError: unknown action, or a start time at or after the ball reaches the plane.
    """
    if not isinstance(trial, Trial):
        raise TypeError(f"trial must be a Trial, got {type(trial).__name__}")
    return _simulator(scene_config, stroke_config).run(trial.ball_after_hit, action, start_time)


def _simulation_fingerprint() -> str:
    """Hash of the simulation's source files (the ball and stroke modules, scene, arm, URDF).

    Part of the cache key, so that a table computed by an older version of the simulation is
    never returned for the current one.
    """
    here = Path(__file__).parent
    files = [here / f"{m}.py" for m in ("ball", "geometry", "scene", "strokes")]
    files += sorted(here.glob("ball_*.py"))  # the ball's concepts, re-exported by ball.py
    files += sorted(here.glob("stroke_*.py"))  # the movements' concepts, re-exported by strokes.py
    files += [here.parent / "wam.py", here.parent / "assets" / "wam7.urdf"]
    h = hashlib.sha256()
    for f in files:
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def default_cache_dir() -> Path:
    """``$HGPDM_CACHE`` if set, else ``~/.cache/hgpdm_torch``."""
    return Path(os.environ.get("HGPDM_CACHE", Path.home() / ".cache" / "hgpdm_torch"))


def _settings_key(scene_config: SceneConfig | None, stroke_config: StrokeConfig | None) -> str:
    """Hash of everything besides the ball that decides a reward: both configurations and the
    simulation's source (:func:`_simulation_fingerprint`)."""
    text = repr((scene_config, stroke_config, _simulation_fingerprint()))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _cell_name(action: str, start_time: float) -> str:
    return f"{action}@{start_time!r}"


_CACHE_FORMAT = 2
"""Version of a reward cache file's layout; files without it (format 1: a bare ``{cell:
reward}``) carry no checksum and are simulated again."""


@dataclass(frozen=True)
class _Stamp:
    """What a cache file's checksum binds its cells to besides the ball: the simulation's source
    (:func:`_simulation_fingerprint`) and the settings folder it lies in."""

    simulation: str
    settings: str

    def checksum(self, ball: str, cells: dict[str, int]) -> str:
        # canonical: sorted keys, no whitespace, so that equal content hashes equally
        text = json.dumps(
            {"ball": ball, "cells": cells, "settings": self.settings,
             "simulation": self.simulation},
            sort_keys=True, separators=(",", ":"),
        )  # fmt: skip
        return hashlib.sha256(text.encode()).hexdigest()


def _read_cells(path: Path, stamp: _Stamp) -> tuple[dict[str, int], str | None]:
    """The verified rewards of one trial's cache file, ``{"action@start_time": +-1}``, and why
    the file was rejected (``None`` when it was not, or when there is no file).

    A rejected file gives no cell: its rewards are simulated again and the file rewritten.
    """
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return {}, None
    except (OSError, ValueError):
        return {}, "unreadable"
    if not isinstance(data, dict):
        return {}, "not reward cache files"
    if "sha256" not in data and "format" not in data:
        return {}, "written by an older version, without a checksum"
    cells = data.get("cells")
    if (
        data.get("format") != _CACHE_FORMAT
        or not isinstance(cells, dict)
        or not all(v in (-1, 1) and not isinstance(v, bool) for v in cells.values())
    ):
        return {}, "not reward cache files"
    if data.get("simulation") != stamp.simulation or data.get("settings") != stamp.settings:
        return {}, "from another version of the simulation"
    if data.get("sha256") != stamp.checksum(path.stem, cells):
        return {}, "with a checksum that does not match their content"
    return cells, None


def _write_cells(path: Path, cells: dict[str, int], stamp: _Stamp) -> None:
    """Add ``cells`` to the cache file of one trial, keeping the verified cells already there,
    with the checksum of the result. Only the calling process writes (workers return their
    rewards), and the file is replaced atomically: a reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    merged = {**_read_cells(path, stamp)[0], **cells}
    data = {"format": _CACHE_FORMAT, "simulation": stamp.simulation,
            "settings": stamp.settings, "cells": merged,
            "sha256": stamp.checksum(path.stem, merged)}  # fmt: skip
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.stem, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, sort_keys=True)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def check_cache_dir(
    cache_dir: str | Path | None = None,
    *,
    scene_config: SceneConfig | None = None,
    stroke_config: StrokeConfig | None = None,
) -> Path:
    """The folder of :func:`reward_table`'s cache for these settings, checked before anything
    is simulated (it need not exist yet).

    Args:
        cache_dir: the cache folder (default :func:`default_cache_dir`).
        scene_config: scene settings; stroke_config: stroke settings (they name the folder).

    Returns:
        ``cache_dir/table_tennis/rewards/<settings>``.

    Raises:
        ValueError: a file where one of the cache's folders belongs, or a folder where a cache
            file belongs (both named by their path): the rewards could not be saved.
    """
    root = Path(cache_dir if cache_dir is not None else default_cache_dir())
    folder = root / "table_tennis" / "rewards" / _settings_key(scene_config, stroke_config)
    for p in (root, root / "table_tennis", folder.parent, folder):
        if p.exists() and not p.is_dir():
            raise ValueError(
                f"reward cache: {p} is a file where the cache keeps a folder; move it away or "
                "choose another cache folder"
            )
    if folder.is_dir():
        with os.scandir(folder) as entries:
            for entry in entries:
                if entry.name.endswith(".json") and entry.is_dir():
                    raise ValueError(
                        f"reward cache: {folder / entry.name} is a folder where a cache file "
                        "belongs; move it away or choose another cache folder"
                    )
    return folder


def _rewards_for(job: tuple) -> np.ndarray:
    """One job of :func:`reward_table`: the rewards ``[C]`` of one ball's ``C`` missing cells.

    The job carries the caller's default dtype and runs under it: a worker (a fresh Ray worker
    above all) must not fall back to its own process's setting.
    """
    pos, vel, spin, cells, scene_config, stroke_config, dtype = job
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        # copies: an array a Ray worker receives is read-only
        ball = B.BallState(torch.tensor(pos), torch.tensor(vel), torch.tensor(spin))
        sim = _simulator(scene_config, stroke_config)
        rewards = [1 if sim.run(ball, action, t0).success else -1 for action, t0 in cells]
    finally:
        torch.set_default_dtype(previous)
    return np.array(rewards, dtype=np.int8)


def reward_table(
    trials: Trials,
    actions: tuple[str, ...] = MOVEMENTS,
    start_times: tuple[float, ...] = DEFAULT_START_TIMES,
    *,
    workers: int = 1,
    executor: Executor | None = None,
    cache_dir: str | Path | None = None,
    scene_config: SceneConfig | None = None,
    stroke_config: StrokeConfig | None = None,
    progress: bool = True,
) -> torch.Tensor:
    """Reward (+1 legal return, -1 otherwise) of every trial x action x start time.

    The thesis enumerates these combinations to learn when and how to act (Sec. 4.3.2).

    Every cell is cached under ``cache_dir`` (default :func:`default_cache_dir`): one small file
    per trial, named by the trial's ball (:meth:`Trials.fingerprints`) in a folder named by both
    configurations and a hash of the simulation's source files (a changed simulation never reads
    an old reward). Only the cells missing from the cache are simulated -- one job per trial,
    written to the cache as soon as it returns -- so an interrupted table resumes where it
    stopped, a table that shares cells with an earlier one (other actions, start times or
    trials) simulates only the new ones, and the executor that filled a cell does not matter:
    the simulation is deterministic and gives the same table on every executor.

    Each file carries the simulation's source hash and a SHA-256 checksum of its rewards, its
    ball and its settings. A file that fails the check (edited by hand, corrupted, written by an
    older version without a checksum, unreadable) is never used: its rewards are simulated
    again and the file rewritten, with one warning per table naming the folder and how many
    files were rejected.

    Args:
        trials: the trials.
        actions: movement names.
        start_times: initiation times relative to the opponent's hit [s].
        workers: jobs at once when no ``executor`` is given (1: in this process; more: local
            processes, see :func:`hgpdm_torch.parallel.get_executor`).
        executor: an :class:`hgpdm_torch.parallel.Executor` to run the jobs on (local processes
            or a Ray cluster); left open for the caller to reuse.
        cache_dir: cache folder.
        scene_config: scene simulation settings.
        stroke_config: stroke simulation settings.
        progress: show a tqdm bar over the trials still to simulate.

    Returns:
        ``[n, len(actions), len(start_times)]`` int8 tensor.

    Raises:
        ValueError: unknown action, bad ``workers`` (or ``workers`` together with
            ``executor``), a start time at or after the moment some trial's ball reaches the
            hitting plane, or a cache path taken by something else (a folder where a cache file
            belongs, a file where a folder belongs; :func:`check_cache_dir`), all before any
            simulation.

    Warns:
        UserWarning: once per table, when cache files were rejected and are simulated again.
    """
    if not isinstance(trials, Trials):
        raise TypeError(f"trials must be Trials, got {type(trials).__name__}")
    actions = tuple(actions)
    for a in actions:
        if a not in MOVEMENTS:
            raise ValueError(f"unknown action {a!r}; expected one of {MOVEMENTS}")
    start_times = tuple(float(t) for t in start_times)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive int, got {workers!r}")
    if executor is not None and not isinstance(executor, Executor):
        raise TypeError(f"executor must be an Executor, got {type(executor).__name__}")
    if executor is not None and workers != 1:
        raise ValueError("give workers or an executor, not both")
    t_cross, _, valid = B.predict_plane_crossing(trials.ball_after_hit, geo.HITTING_PLANE_Y)
    if not bool(valid.all()):
        raise ValueError("some trials' balls never reach the hitting plane")
    if start_times and max(start_times) >= float(t_cross.min()):
        raise ValueError(
            f"start_times must come before every ball reaches the hitting plane (earliest "
            f"{float(t_cross.min()):.3f} s after the opponent's hit), got {max(start_times)}"
        )
    folder = check_cache_dir(cache_dir, scene_config=scene_config, stroke_config=stroke_config)
    stamp = _Stamp(_simulation_fingerprint(), folder.name)
    cells = [(a, t) for a in actions for t in start_times]
    names = [_cell_name(a, t) for a, t in cells]
    keys = trials.fingerprints()
    first = {}  # ball -> its first trial (equal balls are simulated once)
    for i, key in enumerate(keys):
        first.setdefault(key, i)
    known, rejected = {}, {}
    for key in first:
        known[key], why = _read_cells(folder / f"{key}.json", stamp)
        if why is not None:
            rejected[why] = rejected.get(why, 0) + 1
    if rejected:  # one warning for the table, however many files
        reasons = "; ".join(f"{k} {why}" for why, k in rejected.items())
        warnings.warn(
            f"reward cache {folder}: rejected {sum(rejected.values())} of {len(first)} files "
            f"({reasons}); their rewards are simulated again and the files rewritten",
            stacklevel=2,
        )
    balls = [f.detach().cpu().numpy() for f in trials.ball_after_hit]
    jobs, job_keys, dtype = [], [], torch.get_default_dtype()
    for key, i in first.items():
        missing = tuple(c for c, name in zip(cells, names, strict=True) if name not in known[key])
        if missing:
            jobs.append((*(f[i] for f in balls), missing, scene_config, stroke_config, dtype))
            job_keys.append(key)
    if jobs:
        pool = executor if executor is not None else get_executor(workers)
        bar = tqdm(total=len(jobs), disable=not progress, desc="reward table")
        try:
            for key, job, rewards in zip(job_keys, jobs, pool.map(_rewards_for, jobs), strict=True):
                new = {_cell_name(a, t): int(r) for (a, t), r in zip(job[3], rewards, strict=True)}
                known[key].update(new)
                _write_cells(folder / f"{key}.json", new, stamp)
                bar.update()
        finally:
            bar.close()
            if executor is None:
                pool.close()
    table = [[known[key][name] for name in names] for key in keys]
    table = np.array(table, dtype=np.int8).reshape(len(trials), len(actions), len(start_times))
    return torch.from_numpy(table)


def hitting_regions(
    trials: Trials,
    start_time: float = -0.24,
    bins: object = None,
    actions: tuple[str, ...] = MOVEMENTS,
    **reward_kw: object,
) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Success rate of each movement versus the target ``x`` (the thesis's Fig. 3.8 analogue).

    Every trial is played with every movement started at ``start_time`` (240 ms before the
    opponent's hit by default, the thesis's choice) through :func:`reward_table`, and the legal
    returns are averaged over bins of the true target.

    Args:
        trials: the trials.
        start_time: movement initiation relative to the opponent's hit [s].
        bins: ``[K + 1]`` bin edges of the target ``x`` [m] (default: 12 bins over +-1.2 m).
        actions: movements to evaluate.
        **reward_kw: passed to :func:`reward_table` (``workers`` or ``executor``, ``cache_dir``,
            ``progress``, configurations).

    Returns:
        ``centers [K]``, ``{movement: rate [K]}`` (NaN in empty bins) and ``counts [K]``.
    """
    edges = np.linspace(-geo.TARGET_X_MAX, geo.TARGET_X_MAX, 13) if bins is None else bins
    edges = np.asarray(edges, dtype=np.float64)
    if edges.ndim != 1 or edges.size < 2 or not bool(np.all(np.diff(edges) > 0)):
        raise ValueError("bins must be at least two increasing bin edges")
    table = reward_table(trials, actions, (float(start_time),), **reward_kw)  # type: ignore[arg-type]
    targets = trials.targets.numpy()
    which = np.digitize(targets, edges) - 1  # bin of each trial; outside: -1 or K
    k = edges.size - 1
    counts = np.bincount(which[(which >= 0) & (which < k)], minlength=k)
    rates = {}
    for a, name in enumerate(actions):
        won = (table[:, a, 0] > 0).numpy().astype(np.float64)
        inside = (which >= 0) & (which < k)
        sums = np.bincount(which[inside], weights=won[inside], minlength=k)
        with np.errstate(invalid="ignore", divide="ignore"):
            rates[name] = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return 0.5 * (edges[1:] + edges[:-1]), rates, counts
