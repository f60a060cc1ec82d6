"""Monte-Carlo planning decision time per step versus the IDDM's size (thesis Alg. 4.2-4.3).

``python -m benchmarks mcp [--quick]``. Writes ``benchmarks/results/mcp.json``
(``mcp_quick.json`` with ``--quick``). Target: one decision with I = 500 particles in <= 10 ms on
one CPU core (the robot observes every 80 ms).

Setting: an IDDM (continuous target g, Dx = 3, linear measurement kernel, Dz = 15 like the
table-tennis opponent's observations) on ``targeted_movements`` with N transition points, not
fitted (timings do not depend on the fit); the online filter on a K = 25 grid; stopping values
from LSPI on the filtered training movements with rewards by the target's region (three
movements). Decisions are timed on the training beliefs, float64, one thread, best of a few
repeats of the mean over the states. ``cpu`` columns are the process CPU time, which on a shared
machine is closer to what an idle core gives than the wall time:

- ``shared``: the per-decision work every particle shares (K moment-matched predictions and
  their joints with z);
- ``full``: :meth:`MonteCarloPlanner.decide` with all 500 particles (``early_stop=False``);
- ``early``: with Student-t early termination (confidence 0.99, checks every 100 particles),
  and the mean particles used;
- ``points``: ``full`` with the literal sampling chain of Algorithm 4.2 (GP predictions at the
  particles instead of the moment-matched observation distribution).
"""

from __future__ import annotations

import os
import time
from functools import partial

import torch

from benchmarks._common import RESULTS, environment
from hgpdm_torch.datasets import targeted_movements
from hgpdm_torch.decision.basis import RadialBasis
from hgpdm_torch.decision.lspi import lspi
from hgpdm_torch.decision.mcp import Belief, MonteCarloPlanner
from hgpdm_torch.decision.stopping import StoppingProblem, belief_vector
from hgpdm_torch.experiments.table import ResultTable
from hgpdm_torch.inference.intention import OnlineIntentionFilter
from hgpdm_torch.models import IDDM

DX, DZ, LENGTH, PARTICLES = 3, 15, 6, 500


def _setup(n_points: int, k: int):
    """Model, filter, planners and the beliefs to decide on, for ~n_points transition points."""
    num = max(2, round(n_points / (LENGTH - 1)))
    data = targeted_movements(num, LENGTH, DZ, seed=0)
    model = IDDM(data.sequences, data.labels, DX, intention="continuous", measurement="linear")
    grid = torch.linspace(-1.0, 1.0, k)
    f = OnlineIntentionFilter(model, grid, forgetting=0.1, batch_size=num)
    z = torch.stack(data.sequences)
    means, covs, logs = [], [], []
    for t in range(LENGTH):
        f.update(z[:, t])
        if t >= 1:
            means.append(f.mean.clone())
            covs.append(f.cov.clone())
            logs.append(f.log_belief.clone())
    mean, cov, log_prob = torch.stack(means, 1), torch.stack(covs, 1), torch.stack(logs, 1)
    beliefs = belief_vector(mean, cov, log_prob.exp())
    region = torch.bucketize(data.labels, torch.tensor([-1 / 3, 1 / 3]))
    T = beliefs.shape[1]
    right = torch.arange(3)[None, :, None] == region[:, None, None]
    rewards = torch.where(right, torch.linspace(1.0, 0.2, T), torch.tensor(-1.0))
    problem = StoppingProblem(beliefs, rewards.expand(num, 3, T))
    basis = RadialBasis(min(100, num * T), seed=0).fit(beliefs.reshape(-1, beliefs.shape[-1]))
    q = lspi(problem.transitions(problem.enumerate_episodes(), unique=True), features=basis).q
    states = [Belief(mean[i, t], cov[i, t], log_prob[i, t]) for i in range(num) for t in range(T)]
    planner = MonteCarloPlanner(model, f, q, basis, num_particles=PARTICLES)
    literal = MonteCarloPlanner(model, f, q, basis, num_particles=PARTICLES, sampling="points")
    n_trans = model.transition_posterior().train_inputs.shape[0]
    return n_trans, planner, literal, states


def _mean_time(fn, states, repeats: int) -> tuple[float, float]:
    """Best over repeats of the mean wall and CPU time [ms] of ``fn`` over the states."""
    wall = cpu = float("inf")
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        for s in states:
            fn(s)
        wall = min(wall, (time.perf_counter() - w0) / len(states))
        cpu = min(cpu, (time.process_time() - c0) / len(states))
    return 1e3 * wall, 1e3 * cpu


def run(sizes: list[int], k: int, num_states: int, repeats: int) -> ResultTable:
    table = ResultTable(
        f"MCP decision time per step (I = {PARTICLES} particles, K = {k}, Dx = {DX}, Dz = {DZ}, "
        "float64, 1 thread)",
        [
            "N",
            "shared cpu [ms]",
            "full wall [ms]",
            "full cpu [ms]",
            "early cpu [ms]",
            "particles used",
            "points cpu [ms]",
        ],
        meta={
            **environment(),
            "load average": os.getloadavg()[0],
            "states timed": num_states,
            "repeats (best of)": repeats,
            "target": "full <= 10 ms",
        },
    )
    for n in sizes:
        n_trans, planner, literal, states = _setup(n, k)
        states = states[:: max(1, len(states) // num_states)][:num_states]
        gen = torch.Generator().manual_seed(0)
        full_run = partial(planner.decide, early_stop=False, generator=gen)
        early_run = partial(planner.decide, generator=gen)
        points_run = partial(literal.decide, early_stop=False, generator=gen)
        with torch.no_grad():
            planner.decide(states[0], generator=gen)  # warm-up
            _, shared = _mean_time(planner._shared, states, repeats)
            full = _mean_time(full_run, states, repeats)
            used = [early_run(s).particles for s in states]
            _, early = _mean_time(early_run, states, repeats)
            _, points = _mean_time(points_run, states, repeats)
        table.add(
            **{
                "N": n_trans,
                "shared cpu [ms]": shared,
                "full wall [ms]": full[0],
                "full cpu [ms]": full[1],
                "early cpu [ms]": early,
                "particles used": sum(used) / len(used),
                "points cpu [ms]": points,
            }
        )
        print(table.rows[-1], flush=True)
    return table


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    torch.set_num_threads(1)
    torch.set_default_dtype(torch.float64)
    if quick:
        table = run([50], k=9, num_states=5, repeats=1)
    else:
        table = run([100, 250, 500], k=25, num_states=40, repeats=3)
    print(table.to_markdown())
    table.to_json(RESULTS / ("mcp_quick.json" if quick else "mcp.json"))
    return 0
