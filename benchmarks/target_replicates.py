"""Target prediction on fresh draws of the full protocol (issue #14, item 4).

``OMP_NUM_THREADS=1 python -m benchmarks target_replicates [--quick] [--first-seed=S]
[--workers=W] [--ray-address=ADDRESS]`` (about 14 min on 2 cores for 10 replicates; each draws
and simulates 226 strokes; ``--workers`` runs W replicates at once in local processes,
``--ray-address`` on a Ray cluster (``local``, ``auto`` or HOST:PORT), with the same table). Writes
``benchmarks/results/target_replicates.json`` (``..._quick.json`` with ``--quick``,
``..._from{S}.json`` for the seeds ``S .. S + 9`` instead of ``1 .. 10``).

``hgpdm target-prediction`` scores one draw of the protocol (seed 0: train on 100 strokes, test
on the next 126), and that test split was looked at while the models were developed. Here the
same protocol is drawn again with seeds ``1 .. R`` (strokes never used for any choice): each
replicate trains every method on its 100 strokes and scores its 126 test strokes, at 320, 240,
160 and 80 ms before the hit. Methods, with the experiment's settings (the selection the
experiment makes by cross-validation is not repeated):

- GPR: ``WindowGPR`` with its window chosen by its own validation (windows 1-3);
- the GP IDDM, online (linear measurement kernel, ``Dx = 6``, PLS-initialised latents, 40 MAP
  steps, ``eps = 0.2``: the experiment's selected model);
- :class:`~hgpdm_torch.models.LinearIDDM` with its defaults (noise kind and prior by evidence),
  with the evidence temperature and forgetting of its 5-fold cross-validated training beliefs
  (``temperature="cv", forgetting="cv"``), with full noise, with the rank-1 interaction
  (``interaction_rank=1``) without and with that calibration, and calibrated with the noise kind
  and prior chosen by the same cross-validation instead of the evidence (``select="cv"``), with
  rank 0 and 1, and the equal mixture of the beliefs of those two
  (:class:`~hgpdm_torch.inference.BeliefMixture`);
- the phase-aware GP IDDM with a process noise per latent dim (``IDDM(phase_width=...,
  scale_transitions=True)`` with :data:`~hgpdm_torch.decision.beliefs.PHASE_IDDM`, chosen by the
  cross-validation of ``target_sweep --only=phase`` and ``--only="transition scales"``), online
  at ``eps = 0.2``, and the equal mixture of its beliefs
  (:class:`~hgpdm_torch.inference.FilterBeliefs`) with the two linear ones, and its beliefs at
  the evidence temperature fitted on the held-out beliefs of 3-fold cross-validation on the
  training strokes (the experiment's calibration of its selected IDDM; ``meta.replicates``
  holds each replicate's ``T``);
- the ProMP baseline (:class:`~hgpdm_torch.baselines.ProMPRegressor`: the observations jointly
  with the target, conditioned on the prefix with its phase estimated; its options by 5-fold
  cross-validation on the replicate's training strokes, recorded in ``meta.replicates``).

Per method: the MAE [cm] pooled over the ``126 R`` test strokes at each horizon, the ratio to
GPR at 80 ms with a 95% interval from a two-stage bootstrap (replicates, then strokes within
each; it covers the variation of the training draw as well as of the test strokes), how many
replicates have a ratio at most 0.9, and the coverage of the belief's 90% credible set over the
grid (the four horizons pooled; at ``T = 1`` for the GP IDDM; ``meta.replicates`` holds each
replicate's figures and what each LinearIDDM variant chose).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from functools import partial
from pathlib import Path

import torch

from benchmarks.target_sweep import STEPS, abs_errors
from hgpdm_torch.baselines import ProMPRegressor, WindowGPR
from hgpdm_torch.calibration import credible_set, fit_temperature, grid_index
from hgpdm_torch.crossval import contiguous_folds, held_out
from hgpdm_torch.experiments.arguments import add_executor_arguments, connect, positive_int
from hgpdm_torch.experiments.target_prediction import (
    HORIZONS_MS,
    PHASE_IDDM,
    _cv_mae,
    _fit_iddm,
    _online,
    strokes_limit,
)
from hgpdm_torch.inference import BeliefMixture, FilterBeliefs
from hgpdm_torch.models import LinearIDDM
from hgpdm_torch.parallel import Executor
from hgpdm_torch.results import ResultTable
from hgpdm_torch.robots.table_tennis.opponent import sample_strokes

RESULTS = Path(__file__).parent / "results"
METHODS = (
    "GPR (WindowGPR)",
    "GP IDDM online (experiment's model)",
    "LinearIDDM (default: noise kind and prior by evidence)",
    "LinearIDDM, T and eps by CV",
    "LinearIDDM, full noise",
    "LinearIDDM, interaction rank 1",
    "LinearIDDM, interaction rank 1, T and eps by CV",
    "LinearIDDM, noise and prior by CV, T and eps by CV",
    "LinearIDDM, interaction rank 1, noise and prior by CV, T and eps by CV",
    "BeliefMixture of the last two (equal weights)",
    "GP IDDM online, per phase, transition scales (phase width 0.25, noise 0.3, g width x2: CV)",
    "BeliefMixture of the per-phase GP IDDM and the two linear ones (equal weights)",
    "GP IDDM online, per phase, transition scales, T by 3-fold CV",
    "ProMP, phase estimated (basis, phase grid and ridge by 5-fold CV)",
)


def _replicate(seed: int, n_train: int, n_test: int, grid_size: int, steps: int):
    """Absolute errors ``[n_test, 4]`` and 90%-set hits ``[n_test, 4]`` (None for GPR, ProMP) of
    every method on one draw of the protocol, and what each LinearIDDM variant chose (noise
    kind, prior, T, eps and the warnings of its fit)."""
    gen = torch.Generator().manual_seed(seed)
    strokes = sample_strokes(n_train + n_test, generator=gen)
    obs, y = strokes.obs[:n_train], strokes.targets[:n_train]
    test, y_test = strokes.obs[n_train:, : STEPS[-1] + 1], strokes.targets[n_train:]
    lim = strokes_limit(y)
    grid = torch.linspace(-lim, lim, grid_size)
    truth = grid_index(y_test, grid)[:, None].expand(-1, len(STEPS))

    def hits(prob: torch.Tensor) -> torch.Tensor:  # the 90% set holds the true grid value
        return credible_set(prob[:, STEPS], 0.9).gather(-1, truth[..., None])[..., 0]

    out = {}
    gpr = WindowGPR(windows=(1, 2, 3), seed=seed).fit(list(obs), y)
    out[METHODS[0]] = (abs_errors(gpr.predict(test)[0], y_test), None)
    with warnings.catch_warnings():  # 40 MAP steps do not converge; FitResult says so
        warnings.simplefilter("ignore")
        iddm = _fit_iddm(obs, y, "linear", 6, steps, seed)
    mean, _, log_prob = _online(iddm, test, grid, 0.2)
    out[METHODS[1]] = (abs_errors(mean, y_test), hits(log_prob.exp()))
    choices, fitted = {}, []
    calibrate = {"temperature": "cv", "forgetting": "cv"}
    variants = ({}, calibrate, {"noise": "full"}, {"interaction_rank": 1},
                {"interaction_rank": 1, **calibrate}, {"select": "cv", **calibrate},
                {"interaction_rank": 1, "select": "cv", **calibrate})  # fmt: skip
    for name, options in zip(METHODS[2:9], variants, strict=True):
        with warnings.catch_warnings(record=True) as caught:  # edge choices: recorded below
            warnings.simplefilter("always")
            model = LinearIDDM(**options).fit(obs, y)
        choices[name] = {"noise": model.noise_kind, "prior": list(model.prior),
                         "temperature": model.temperature, "forgetting": model.forgetting,
                         "warnings": [str(w.message) for w in caught]}  # fmt: skip
        fitted.append(model)
        belief = model.beliefs(test, grid)
        out[name] = (abs_errors(belief.mean[..., 0], y_test), hits(belief.prob))
    belief = BeliefMixture(fitted[-2:]).beliefs(test, grid)
    out[METHODS[9]] = (abs_errors(belief.mean[..., 0], y_test), hits(belief.prob))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        phased = _fit_iddm(obs, y, "linear", 6, steps, seed, **PHASE_IDDM)
    member = FilterBeliefs(phased, forgetting=0.2)
    belief = member.beliefs(test, grid)
    out[METHODS[10]] = (abs_errors(belief.mean[..., 0], y_test), hits(belief.prob))
    belief = BeliefMixture([member, *fitted[-2:]]).beliefs(test, grid)
    out[METHODS[11]] = (abs_errors(belief.mean[..., 0], y_test), hits(belief.prob))
    # its evidence temperature from the held-out beliefs of 3-fold CV on the training strokes
    # (the experiment's calibration of its selected IDDM)
    folds = contiguous_folds(n_train, 3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, logs, held_truth = _cv_mae(obs, y, folds, "linear", 6, steps, seed, "pls", grid, 0.2,
                                      **PHASE_IDDM)  # fmt: skip
    temperature = fit_temperature(logs, held_truth)
    choices[METHODS[12]] = {"temperature": temperature}
    belief = FilterBeliefs(phased, forgetting=0.2, temperature=temperature).beliefs(test, grid)
    out[METHODS[12]] = (abs_errors(belief.mean[..., 0], y_test), hits(belief.prob))
    promp = ProMPRegressor(folds=5, seed=seed).fit(list(obs), y)
    choices[METHODS[13]] = {k: str(v) for k, v in promp.options.items()}
    out[METHODS[13]] = (abs_errors(promp.predict(test)[0], y_test), None)
    return out, choices


def _ratio_interval(
    err: list[torch.Tensor], ref: list[torch.Tensor], n_boot: int, seed: int
) -> tuple[float, float]:
    """95% two-stage bootstrap interval of ``sum err / sum ref`` at 80 ms: replicates drawn with
    replacement, then the strokes of each drawn replicate (paired between the two methods)."""
    gen = torch.Generator().manual_seed(seed)
    e, r = torch.stack([x[:, -1] for x in err]), torch.stack([x[:, -1] for x in ref])
    reps, n = e.shape
    which = torch.randint(reps, (n_boot, reps), generator=gen)
    strokes = torch.randint(n, (n_boot, reps, n), generator=gen)
    pick_e = e[which[..., None], strokes].sum((1, 2))
    pick_r = r[which[..., None], strokes].sum((1, 2))
    lo, hi = torch.quantile(pick_e / pick_r, torch.tensor([0.025, 0.975], dtype=e.dtype))
    return float(lo), float(hi)


def _timed_replicate(k: int, seed: int, n_train: int, n_test: int, grid_size: int, steps: int):
    """Replicate ``k`` (its draw seeded by ``seed``): :func:`_replicate` and its wall time [s]
    (one executor job)."""
    start = time.time()
    out, choices = _replicate(seed, n_train, n_test, grid_size, steps)
    return out, choices, time.time() - start


def run(
    quick: bool = False,
    replicates: int = 10,
    first_seed: int = 1,
    executor: Executor | None = None,
) -> ResultTable:
    """The table; ``executor`` (:func:`~hgpdm_torch.parallel.get_executor`) runs the replicates
    at once, in this process's settings and default dtype (each is seeded by its own seed: the
    same table as one after the other)."""
    if quick:
        replicates, n_train, n_test, grid_size, steps = 2, 20, 10, 13, 5
    else:
        n_train, n_test, grid_size, steps = 100, 126, 25, 40
    seeds = range(first_seed, first_seed + replicates)
    errors: dict[str, list] = {m: [] for m in METHODS}
    covered: dict[str, list] = {m: [] for m in METHODS}
    table = ResultTable(
        f"Target prediction on {replicates} fresh draws of the protocol "
        f"(train {n_train} / test {n_test} strokes each), MAE [cm]",
        [
            "method",
            *(f"{h} ms" for h in HORIZONS_MS),
            "ratio to GPR @80 ms [95%]",
            "replicates <= 0.9",
            "90% set coverage [%]",
        ],  # fmt: skip
        meta={
            "seeds": list(seeds),
            "n_train": n_train,
            "n_test": n_test,
            "replicates": {},
        },  # fmt: skip
    )
    job = partial(_timed_replicate, n_train=n_train, n_test=n_test, grid_size=grid_size,
                  steps=steps)  # fmt: skip
    results = held_out([(seed,) for seed in seeds], job, executor=executor, item="replicate")
    for seed, (out, choices, seconds) in zip(seeds, results, strict=True):
        ref = out[METHODS[0]][0][:, -1].sum()
        table.meta["replicates"][seed] = {
            "seconds": round(seconds, 1),
            "phase_iddm_temperature": choices.pop(METHODS[12])["temperature"],
            "linear_iddm_choices": choices,
            "mae_80ms": {m: float(e[:, -1].mean()) for m, (e, _) in out.items()},
            "ratio_80ms": {m: float(e[:, -1].sum() / ref) for m, (e, _) in out.items()},
        }
        for m, (e, hit) in out.items():
            errors[m].append(e)
            covered[m].append(hit)
        rep = table.meta["replicates"][seed]
        print(f"replicate {seed} ({rep['seconds']} s), ratio to GPR at 80 ms: "
              f"{rep['ratio_80ms']}", file=sys.stderr)  # fmt: skip
    for m in METHODS:
        err = torch.cat(errors[m])
        ratios = [r["ratio_80ms"][m] for r in table.meta["replicates"].values()]
        row = {"method": m, **{f"{h} ms": round(float(v), 1)
                               for h, v in zip(HORIZONS_MS, err.mean(0), strict=True)}}  # fmt: skip
        if m != METHODS[0]:
            lo, hi = _ratio_interval(errors[m], errors[METHODS[0]], 2000, 0)
            ratio = float(err[:, -1].sum() / torch.cat(errors[METHODS[0]])[:, -1].sum())
            row["ratio to GPR @80 ms [95%]"] = f"{ratio:.2f} [{lo:.2f}, {hi:.2f}]"
            row["replicates <= 0.9"] = f"{sum(r <= 0.9 for r in ratios)}/{replicates}"
        if covered[m][0] is not None:
            hits = torch.cat(covered[m]).double()
            row["90% set coverage [%]"] = round(100 * float(hits.mean()), 1)
        table.add(**row)
    return table


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks target_replicates")
    parser.add_argument("--quick", action="store_true", help="smoke mode: 2 small replicates")
    parser.add_argument(
        "--first-seed", type=positive_int, default=1,
        help="the replicates S .. S + 9 (a confirmation on draws never looked at)",
    )  # fmt: skip
    add_executor_arguments(parser, "the replicates")
    args = parser.parse_args(argv)
    quick, first = args.quick, args.first_seed
    pool = connect(parser, args.workers, args.ray_address, local=True)
    try:
        table = run(quick=quick, first_seed=first, executor=pool)
    finally:
        if pool is not None:
            pool.close()
    print(table.to_markdown())
    name = "target_replicates" + ("_quick" if quick else "") + (f"_from{first}" if first != 1
                                                                 else "")  # fmt: skip
    table.to_json(RESULTS / f"{name}.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
