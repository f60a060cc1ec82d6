r"""``hgpdm demo``: the anticipatory table-tennis player, end to end (thesis Ch. 3-4).

1. Simulate opponent strokes and the reward of every movement (forehand, middle, backhand)
   started at every decision time (320 ... 0 ms before the opponent's hit) in the SAPIEN scene
   with the Barrett WAM (:func:`~hgpdm_torch.robots.table_tennis.trials.reward_table`, cached on
   disk).
2. Split the strokes inside the robot's hitting region into training and test strokes.
3. Fit the IDDM (continuous target, Ch. 3) on the training strokes and on further opponent
   strokes that the robot only watched (observations and targets, no SAPIEN: watching the
   opponent is cheap, trying movements is not); the online filter
   (Algorithm 3.2) gives every stroke's belief (latent state and target histogram) at every
   decision time.
4. Learn when and how to hit (Ch. 4): LSPI (Algorithm 4.1) on the enumerated training episodes,
   and Monte-Carlo planning (Algorithms 4.2-4.3) on top of LSPI's stopping values.
5. Play the test rallies: at each decision time the player, with MCP, waits or starts a movement;
   the chosen movement is executed in SAPIEN and the ball is returned or missed.
6. Print the return rates against the baselines (each single movement started 240 ms before the
   hit; the best movement chosen at a fixed time; LSPI) and save figures: return rates, one
   played rally in 3-D and the belief over the target during that stroke.

``hgpdm demo --full`` runs the whole Sec. 4.3 experiment instead (``hgpdm anticipation --full``).
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..decision.basis import RadialBasis
from ..decision.lspi import lspi
from ..decision.mcp import MonteCarloPlanner
from ..decision.stopping import StoppingProblem
from ..parallel import Executor, ray_address_type
from . import anticipation as ant
from .arguments import non_negative_int, output_folder, positive_int, random_seed
from .dtype import float64_default
from .table import ResultTable

__all__ = ["Rally", "DemoResult", "main", "plot_demo", "run_demo"]


@dataclass
class Rally:
    """One test stroke played by the MCP player in SAPIEN.

    Attributes:
        trial: index of the stroke among the simulated trials.
        target: the opponent's true target ``x`` on the hitting plane [m].
        action: the movement started; start_time: when, relative to the opponent's hit [s].
        outcome: the :class:`~hgpdm_torch.robots.table_tennis.strokes.StrokeOutcome` of SAPIEN.
    """

    trial: int
    target: float
    action: str
    start_time: float
    outcome: object


@dataclass
class DemoResult:
    """What :func:`run_demo` returns: the table, the played rallies and the beliefs to draw.

    ``target_probs [n_test, T, K]`` is the belief over the target grid ``grid [K]`` of each test
    stroke at the ``T`` decision times ``start_times``.
    """

    table: ResultTable
    rallies: list[Rally]
    grid: torch.Tensor
    start_times: tuple[float, ...]
    target_probs: torch.Tensor
    meta: dict = field(default_factory=dict)


def run_demo(
    *,
    num_trials: int = 48,
    watched: int = 150,
    test_fraction: float = 1 / 3,
    config: ant.AnticipationConfig | None = None,
    workers: int | None = None,
    executor: Executor | None = None,
    seed: int = 0,
    cache_dir: str | Path | None = None,
    progress: bool = False,
) -> DemoResult:
    """Train the anticipatory player on simulated strokes and play the test rallies in SAPIEN.

    Args:
        num_trials: opponent strokes played in SAPIEN (before excluding those outside the
            robot's hitting region).
        watched: further opponent strokes the IDDM is trained on (no robot movements).
        test_fraction: share of the valid strokes held out as test rallies.
        config: IDDM, basis, LSPI and MCP settings (default: the full experiment's with 20
            RBF centres; learning takes seconds, the SAPIEN simulation minutes).
        workers: SAPIEN processes for the reward table (default: all cores, at most 4).
        executor: an :class:`~hgpdm_torch.parallel.Executor` (e.g. a Ray cluster) to simulate
            the reward table on instead of ``workers`` local processes; left open.
        seed: seeds the strokes, the split and the planner.
        cache_dir: reward-table cache (default ``$HGPDM_CACHE`` or ``~/.cache/hgpdm_torch``).
        progress: tqdm bars.

    Returns:
        A :class:`DemoResult`.

    Raises:
        ValueError: bad sizes (``num_trials``, ``watched``, ``workers``, ``test_fraction``
            outside (0, 1)), ``workers`` with an ``executor``, or too few valid strokes to split.
    """
    from ..robots.table_tennis import strokes
    from ..robots.table_tennis.trials import (
        DEFAULT_START_TIMES,
        evaluate,
        make_trials,
        reward_table,
    )

    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction!r}")
    for name, value, low in (("num_trials", num_trials, 1), ("watched", watched, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise ValueError(f"workers must be a positive int or None, got {workers!r}")
    if workers is not None and executor is not None:
        raise ValueError("give workers or an executor, not both")
    config = config or ant.AnticipationConfig(centres=20, iddm_trials=10_000, seed=seed)
    local = {"workers": workers or max(1, min(4, os.cpu_count() or 1))}
    pool = local if executor is None else {"executor": executor}
    movements = tuple(strokes.MOVEMENTS)
    if movements != ant.MOVEMENTS:
        raise RuntimeError(f"robot movements {movements} differ from actions {ant.MOVEMENTS}")
    start_times = DEFAULT_START_TIMES
    clock = time.perf_counter()
    with float64_default():
        trials = make_trials(num_trials, seed=seed, progress=progress)
        rewards = reward_table(
            trials, movements, start_times, cache_dir=cache_dir, progress=progress, **pool
        ).to(torch.float64)
        t_sim = time.perf_counter() - clock
        valid = torch.nonzero(ant.valid_trials(rewards)).flatten()
        n_test = round(test_fraction * len(valid))
        if n_test < 1 or len(valid) - n_test < 4:
            raise ValueError(
                f"only {len(valid)} of {num_trials} strokes are inside the hitting region; "
                "simulate more (num_trials)"
            )
        gen = torch.Generator().manual_seed(seed)
        perm = valid[torch.randperm(len(valid), generator=gen)]
        test, train = perm[:n_test].sort().values, perm[n_test:].sort().values

        clock = time.perf_counter()
        obs, targets, iddm_train = trials.obs, trials.targets, train
        if watched:
            seen = make_trials(watched, seed=seed + 1, progress=progress)
            if not torch.equal(seen.obs_times, trials.obs_times):
                raise RuntimeError("watched strokes must share the trials' observation times")
            obs, targets = torch.cat([obs, seen.obs]), torch.cat([targets, seen.targets])
            iddm_train = torch.cat([train, num_trials + torch.arange(watched)])
        steps_at = ant.decision_indices(trials.obs_times, start_times)
        beliefs = ant.fit_beliefs(obs, targets, steps_at, iddm_train, test, config)
        vectors = beliefs.vectors()[:num_trials]
        problem = StoppingProblem(vectors, rewards)
        train_p, test_p = problem.subset(train), problem.subset(test)
        basis = RadialBasis(config.centres, seed=seed, bias=True).fit(
            train_p.beliefs.reshape(-1, vectors.shape[-1])
        )
        enumerated = train_p.transitions(train_p.enumerate_episodes(), unique=True)
        q = lspi(enumerated, features=basis, ridge=config.ridge).q
        planner = MonteCarloPlanner(
            beliefs.model, beliefs.belief_filter, q, basis,
            num_particles=config.particles, confidence=config.confidence,
        )  # fmt: skip
        t_learn = time.perf_counter() - clock

        table = ResultTable(
            f"hgpdm demo: anticipatory table tennis, {len(test)} test rallies "
            f"({len(train)} training strokes)",
            ["player", "returns", "rate", "played in"],
            meta={"num_trials": num_trials, "watched": watched, "valid": len(valid), "seed": seed},
        )
        single = start_times.index(ant.SINGLE_TIME)
        for a, name in enumerate(movements):
            won = int((test_p.rewards[:, a, single] > 0).sum())
            table.add(player=f"always {name} @240ms", returns=won, rate=won / len(test))
        for s in ant.ORACLE_TIMES:
            step = start_times.index(s)
            q_t = ant.stop_only_q(train_p, step, basis, config.ridge)
            won = ant.successes(test_p.run(ant.fixed_time_policy(q_t, basis, step)))
            name = f"best movement @{round(-1000 * s)}ms"
            table.add(player=name, returns=won, rate=won / len(test))
        won = ant.successes(test_p.run(ant.greedy_policy(q, basis, test_p)))
        table.add(player="LSPI", returns=won, rate=won / len(test))
        for row in table.rows:
            row["played in"] = "reward table (SAPIEN)"

        # the MCP player's decisions, each executed in SAPIEN
        clock = time.perf_counter()
        decided = test_p.run(ant.mcp_policy(planner, beliefs, test, test_p.horizon, gen))
        t_plan = time.perf_counter() - clock
        clock = time.perf_counter()
        rallies = []
        for j, i in enumerate(test.tolist()):
            action = movements[int(decided.stop_action[j]) - 1]
            t0 = start_times[int(decided.stop_step[j])]
            outcome = evaluate(trials[i], action, t0)
            rallies.append(Rally(i, float(trials.targets[i]), action, t0, outcome))
        t_play = time.perf_counter() - clock
        won = sum(r.outcome.success for r in rallies)
        table.add(player="MCP", returns=won, rate=won / len(test), **{"played in": "SAPIEN"})
        # the scene is deterministic: each live rally must reproduce the reward the stopping
        # problem gave the planner's (step, action) decision
        agree = sum(r.outcome.success == bool(decided.reward[j] > 0) for j, r in enumerate(rallies))
        probs = beliefs.log_prob[test].exp()
    meta = {
        "simulate [s]": t_sim,
        "learn [s]": t_learn,
        "MCP per decision [ms]": 1e3 * t_plan / max(1, int((decided.stop_step + 1).sum())),
        "play [s]": t_play,
        "live = table": f"{agree}/{len(rallies)}",
    }
    table.meta.update(meta)
    grid = torch.linspace(-config.grid_max, config.grid_max, config.grid_size)
    return DemoResult(table, rallies, grid, start_times, probs, meta)


def plot_demo(result: DemoResult, out: str | Path) -> list[Path]:
    """Save the return rates, one played rally in 3-D and its belief over the target (PNGs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..robots.table_tennis.draw import MOVEMENT_COLORS, draw_stroke, draw_table
    from ..robots.wam import WAM

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    names, rates = result.table.column("player"), result.table.column("rate")
    fig, ax = plt.subplots(figsize=(8, 3.6))
    colours = ["0.7"] * 3 + ["tab:blue"] * 3 + ["tab:orange", "tab:green"]
    ax.bar(range(len(names)), rates, color=colours[: len(names)])
    ax.set_xticks(range(len(names)), [n.replace(" ", "\n") for n in names], fontsize=8)
    ax.set_ylabel("successful returns (test rallies)")
    ax.set_ylim(0, 1)
    ax.set_title(result.table.title, fontsize=9)
    fig.tight_layout()
    paths.append(out / "return_rates.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    # the first returned rally (else the first one) and the belief that led to it
    j = next((k for k, r in enumerate(result.rallies) if r.outcome.success), 0)
    rally = result.rallies[j]
    fig = plt.figure(figsize=(11, 4.2))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    draw_table(ax3)
    draw_stroke(ax3, rally.outcome, WAM(), color=MOVEMENT_COLORS[rally.action], label=rally.action)
    ax3.set_title(
        f"stroke {rally.trial}: {rally.action} started {round(-1000 * rally.start_time)} ms "
        f"before the hit -> {'returned' if rally.outcome.success else 'missed'}",
        fontsize=9,
    )
    ax = fig.add_subplot(1, 2, 2)
    probs = result.target_probs[j]
    for t, s in enumerate(result.start_times):
        ax.plot(result.grid, probs[t], label=f"{round(-1000 * s)} ms before the hit")
    ax.axvline(rally.target, color="k", ls="--", lw=1, label="true target")
    ax.set(xlabel="target x on the hitting plane [m]", ylabel="belief (online IDDM)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / "rally.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths


def main(argv: list[str]) -> int:
    """CLI entry: ``hgpdm demo [--trials N] [--watched M] [--workers W] [--ray-address ADDRESS]
    [--seed S] [--out DIR] [--cache-dir DIR] [--full] [--progress]``."""
    parser = argparse.ArgumentParser(prog="hgpdm demo", description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=positive_int, default=None, help="strokes played (48)")
    parser.add_argument(
        "--watched",
        type=non_negative_int,
        default=None,
        help="further strokes the IDDM learns from (150)",
    )
    parser.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="SAPIEN processes (all cores, at most 4); with --ray-address as in anticipation",
    )
    parser.add_argument(
        "--ray-address",
        type=ray_address_type,
        default=None,
        help="simulate the reward table on Ray: 'local', 'auto' or HOST:PORT of a head node",
    )
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--out", type=output_folder, default="hgpdm_demo_output")
    parser.add_argument("--cache-dir", type=output_folder, default=None)
    parser.add_argument(
        "--full", action="store_true", help="run the full Sec. 4.3 experiment instead"
    )
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    if args.full and (args.trials is not None or args.watched is not None):
        parser.error("--trials and --watched set the demo's sizes; --full uses the thesis's")
    if args.full:
        extra = ["--out", str(args.out), "--seed", str(args.seed)]
        if args.ray_address is None:
            extra += ["--workers", str(args.workers or max(1, os.cpu_count() or 1))]
        else:
            extra += ["--ray-address", args.ray_address]
            extra += ["--workers", str(args.workers)] if args.workers else []
        extra += ["--progress"] if args.progress else []
        extra += ["--cache-dir", str(args.cache_dir)] if args.cache_dir else []
        return ant.main(["--full", *extra])
    executor = ant.connect(parser, args.workers, args.ray_address)
    try:
        result = run_demo(
            num_trials=48 if args.trials is None else args.trials,
            watched=150 if args.watched is None else args.watched,
            workers=None if executor is not None else args.workers, executor=executor,
            seed=args.seed, cache_dir=args.cache_dir, progress=args.progress,
        )  # fmt: skip
    finally:
        if executor is not None:
            executor.close()
    print(result.table.to_markdown(".3g"))
    print()
    print(", ".join(f"{k}: {v:.3g}" if isinstance(v, float) else f"{k}: {v}"
                    for k, v in result.meta.items()))  # fmt: skip
    out = Path(args.out)
    result.table.to_json(out / "demo.json")
    for path in plot_demo(result, out):
        print(f"saved {path}")
    return 0
