"""Table-tennis trials and the enumerated reward table of thesis Sec. 4.3.2.

A trial is one stroke of the simulated opponent (:mod:`.opponent`): the observations the robot sees
before the opponent's hit, the true target and the ball leaving the opponent's racket. Evaluating a
trial runs the SAPIEN scene with one of the robot's movements initiated at one time; the reward is
+1 for a legal return and -1 otherwise, as in the thesis. :func:`reward_table` enumerates every
(trial, movement, start time) combination, in parallel over processes, cached on disk.
"""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from . import ball as B
from . import geometry as geo
from .opponent import OpponentConfig, sample_strokes
from .scene import SceneConfig, TableTennisScene
from .strokes import MOVEMENTS, StrokeConfig, StrokeOutcome, StrokePlanner, execute_stroke

__all__ = [
    "DEFAULT_START_TIMES",
    "Trial",
    "Trials",
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

    def fingerprint(self) -> str:
        """Hash of the balls that define the trials (the cache key's data part)."""
        h = hashlib.sha256()
        for f in self.ball_after_hit:
            h.update(np.ascontiguousarray(f.detach().cpu().numpy(), dtype=np.float64).tobytes())
        return h.hexdigest()[:16]


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
    key = (repr(scene_config), repr(stroke_config))
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
        scene_config, stroke_config: settings (defaults when ``None``).

    Raises:
        ValueError: unknown action, or a start time at or after the ball reaches the plane.
    """
    if not isinstance(trial, Trial):
        raise TypeError(f"trial must be a Trial, got {type(trial).__name__}")
    return _simulator(scene_config, stroke_config).run(trial.ball_after_hit, action, start_time)


def _simulation_fingerprint() -> str:
    """Hash of the simulation's source files (ball, scene, strokes, arm, URDF).

    Part of the cache key, so that a table computed by an older version of the simulation is
    never returned for the current one.
    """
    here = Path(__file__).parent
    files = [here / f"{m}.py" for m in ("ball", "geometry", "scene", "strokes")]
    files += [here.parent / "wam.py", here.parent / "assets" / "wam7.urdf"]
    h = hashlib.sha256()
    for f in files:
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


def default_cache_dir() -> Path:
    """``$HGPDM_CACHE`` if set, else ``~/.cache/hgpdm_torch``."""
    return Path(os.environ.get("HGPDM_CACHE", Path.home() / ".cache" / "hgpdm_torch"))


def _rewards_for(args: tuple) -> np.ndarray:
    pos, vel, spin, actions, start_times, scene_config, stroke_config = args
    ball = B.BallState(torch.as_tensor(pos), torch.as_tensor(vel), torch.as_tensor(spin))
    sim = _simulator(scene_config, stroke_config)
    out = np.empty((len(actions), len(start_times)), dtype=np.int8)
    for a, action in enumerate(actions):
        for s, t0 in enumerate(start_times):
            out[a, s] = 1 if sim.run(ball, action, t0).success else -1
    return out


def reward_table(
    trials: Trials,
    actions: tuple[str, ...] = MOVEMENTS,
    start_times: tuple[float, ...] = DEFAULT_START_TIMES,
    *,
    workers: int = 1,
    cache_dir: str | Path | None = None,
    scene_config: SceneConfig | None = None,
    stroke_config: StrokeConfig | None = None,
    progress: bool = True,
) -> torch.Tensor:
    """Reward (+1 legal return, -1 otherwise) of every trial x action x start time.

    The thesis enumerates these combinations to learn when and how to act (Sec. 4.3.2). Results
    are cached under ``cache_dir`` (default :func:`default_cache_dir`) keyed by the trials'
    balls, the actions, the start times, both configurations and a hash of the simulation's
    source files (a changed simulation never reads an old table).

    Args:
        trials: the trials.
        actions: movement names.
        start_times: initiation times relative to the opponent's hit [s].
        workers: processes to use (1: in this process).
        cache_dir: cache folder.
        scene_config, stroke_config: simulation settings.
        progress: show a tqdm bar over trials.

    Returns:
        ``[n, len(actions), len(start_times)]`` int8 tensor.

    Raises:
        ValueError: unknown action, bad ``workers``, or a start time at or after the moment some
            trial's ball reaches the hitting plane.
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
    t_cross, _, valid = B.predict_plane_crossing(trials.ball_after_hit, geo.HITTING_PLANE_Y)
    if not bool(valid.all()):
        raise ValueError("some trials' balls never reach the hitting plane")
    if start_times and max(start_times) >= float(t_cross.min()):
        raise ValueError(
            f"start_times must come before every ball reaches the hitting plane (earliest "
            f"{float(t_cross.min()):.3f} s after the opponent's hit), got {max(start_times)}"
        )
    key = hashlib.sha256(
        repr(
            (
                trials.fingerprint(),
                actions,
                start_times,
                scene_config,
                stroke_config,
                _simulation_fingerprint(),
            )
        ).encode()
    ).hexdigest()[:24]
    path = Path(cache_dir if cache_dir is not None else default_cache_dir())
    path = path / "table_tennis" / f"rewards_{key}.npy"
    if path.exists():
        return torch.from_numpy(np.load(path))
    jobs = [
        (
            trials.ball_after_hit.pos[i].numpy(),
            trials.ball_after_hit.vel[i].numpy(),
            trials.ball_after_hit.spin[i].numpy(),
            actions,
            start_times,
            scene_config,
            stroke_config,
        )
        for i in range(len(trials))
    ]
    bar = tqdm(total=len(jobs), disable=not progress, desc="reward table")
    if workers == 1:
        rows = []
        for job in jobs:
            rows.append(_rewards_for(job))
            bar.update()
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            rows = []
            for row in pool.map(_rewards_for, jobs):
                rows.append(row)
                bar.update()
    bar.close()
    table = np.stack(rows) if rows else np.empty((0, len(actions), len(start_times)), np.int8)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npy")
    np.save(tmp, table)
    tmp.replace(path)
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
        **reward_kw: passed to :func:`reward_table` (``workers``, ``cache_dir``, ``progress``,
            configurations).

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
