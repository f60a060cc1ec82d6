"""Why the online IDDM does not reach 0.9 x GPR on target prediction (issue #14, item 4).

``OMP_NUM_THREADS=1 python -m benchmarks target_sweep [--quick] [--only=TEXT]`` (10-40 min on a
loaded 2-core machine). Writes ``benchmarks/results/target_sweep.json`` (``..._quick.json`` with
``--quick``; with ``--only=TEXT`` only the base row and the variants whose name holds TEXT, into
``target_sweep_TEXT.json``).

Only the 100 *training* strokes of ``hgpdm target-prediction`` are used (the test strokes stay
untouched): 5-fold cross-validation, the online IDDM of the experiment (PLS-initialised latents,
linear measurement kernel, Dx = 6, 40 MAP steps, ``eps = 0.2``, 25-value grid) against the
experiment's GPR (``WindowGPR``, window chosen by its own validation) fitted on the same folds.
Each row changes one setting of the IDDM (model, learning or inference) and reports the
cross-validated MAE [cm] at 320/240/160/80 ms before the hit, the ratio to GPR at 80 ms and the
paired difference IDDM - GPR at 80 ms (mean +- SEM over the 100 strokes). Further rows:

- ``T by inner CV``: the evidence temperature fitted (maximum likelihood of the true grid value,
  :func:`~hgpdm_torch.calibration.fit_temperature`) on inner 4-fold CV beliefs of
  each outer training part, with ``eps = 0``;
- ``evidence of step t only``: the base model's posterior mean at 80 ms when the belief keeps the
  evidence of one step only (``eps = 0``): how much each observation says about the target.

The thesis's shape needs the ratio at 80 ms at most 0.9.
"""

from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path
from typing import Any

import torch

from hgpdm_torch.baselines import WindowGPR
from hgpdm_torch.calibration import fit_temperature, grid_index
from hgpdm_torch.experiments.target_prediction import (
    HORIZONS_MS,
    _online,
    strokes_limit,
)
from hgpdm_torch.inference import OnlineIntentionFilter
from hgpdm_torch.models import HGPDM, IDDM, supervised_init
from hgpdm_torch.results import ResultTable
from hgpdm_torch.robots.table_tennis.opponent import sample_strokes

RESULTS = Path(__file__).parent / "results"
STEPS = [1, 2, 3, 4]  # observation index of 320, 240, 160, 80 ms before the hit
BASE: dict[str, Any] = {
    "dx": 6, "kernel": "linear", "steps": 40, "alpha": (0.9, 0.3, 0.1, 1e-2),
    "alpha_g": (4.0, 0.1), "eps": 0.2, "features": None, "back_constraint": None,
    "learn_alpha": False, "model": IDDM, "phase_width": None, "scale_transitions": False,
}  # fmt: skip
#: (row name, changes to BASE)
VARIANTS: list[tuple[str, dict[str, Any]]] = [
    ("experiment's IDDM (linear, Dx 6, 40 steps)", {}),
    ("10 MAP steps", {"steps": 10}),
    ("150 MAP steps", {"steps": 150}),
    ("Dx 3", {"dx": 3}),
    ("Dx 8", {"dx": 8}),
    ("Dx 10", {"dx": 10}),
    ("RBF measurement, Dx 8", {"kernel": "rbf", "dx": 8}),
    ("g width x2 (alpha_g 1)", {"alpha_g": (1.0, 0.1)}),
    ("g width /2 (alpha_g 16)", {"alpha_g": (16.0, 0.1)}),
    ("process noise 1e-3", {"alpha": (0.9, 0.3, 0.1, 1e-3)}),
    ("process noise 1e-1", {"alpha": (0.9, 0.3, 0.1, 1e-1)}),
    ("process noise 3e-1", {"alpha": (0.9, 0.3, 0.1, 3e-1)}),
    ("learned transition kernel and noise", {"learn_alpha": True}),
    ("kernel back-constraint", {"back_constraint": "kernel"}),
    ("no forgetting (eps 0)", {"eps": 0.0}),
    ("forgetting eps 0.5", {"eps": 0.5}),
    ("racket features only (9)", {"features": slice(6, 15)}),
    ("process noise 1e-1, g width x2", {"alpha": (0.9, 0.3, 0.1, 1e-1), "alpha_g": (1.0, 0.1)}),
    # RBF + linear in x and g (the H-GPDM's continuous kernel; the filter's generic path)
    ("H-GPDM transition (RBF + linear x, g)", {"model": HGPDM, "alpha_g": (4.0, 1.0)}),
    (
        "H-GPDM transition, process noise 1e-1",
        {"model": HGPDM, "alpha": (0.9, 0.3, 0.1, 1e-1), "alpha_g": (4.0, 1.0)},
    ),
    # the transition kernel times an RBF over the frame index (IDDM(phase_width=...))
    *((f"phase width {w}", {"phase_width": w}) for w in (0.25, 0.5, 1.0, 2.0, 4.0)),
    *(
        (
            f"phase width {w}, process noise {a4:g}, g width x2",
            {"phase_width": w, "alpha": (0.9, 0.3, 0.1, a4), "alpha_g": (1.0, 0.1)},
        )
        for w, a4 in ((0.25, 0.1), (0.5, 0.1), (1.0, 0.1), (0.5, 0.3), (0.5, 0.03))
    ),
    ("phase width 0.5, process noise 0.1", {"phase_width": 0.5, "alpha": (0.9, 0.3, 0.1, 0.1)}),
    *(
        (
            f"phase width 0.25, process noise 0.1, g width x2, {name}",
            {"phase_width": 0.25, "alpha": (0.9, 0.3, 0.1, 0.1), "alpha_g": (1.0, 0.1), **change},
        )
        for name, change in (
            ("Dx 4", {"dx": 4}),
            ("Dx 8", {"dx": 8}),
            ("Dx 10", {"dx": 10}),
            ("no forgetting", {"eps": 0.0}),
            ("80 MAP steps", {"steps": 80}),
        )
    ),
    # an output scale per latent dim of the transition GP (IDDM(scale_transitions=True)): a
    # process noise per latent dim
    *(
        (
            f"phase width 0.25, process noise {a4:g}, g width x2, transition scales",
            {
                "phase_width": 0.25,
                "alpha": (0.9, 0.3, 0.1, a4),
                "alpha_g": (1.0, 0.1),
                "scale_transitions": True,
            },
        )  # fmt: skip
        for a4 in (0.1, 0.3, 0.03, 1.0)
    ),
    *(
        (
            f"phase width 0.25, process noise 0.3, g width x2, transition scales, {name}",
            {
                "phase_width": 0.25,
                "alpha": (0.9, 0.3, 0.1, 0.3),
                "alpha_g": (1.0, 0.1),
                "scale_transitions": True,
                **change,
            },
        )  # fmt: skip
        for name, change in (
            ("Dx 4", {"dx": 4}),
            ("Dx 8", {"dx": 8}),
            ("phase width 0.5", {"phase_width": 0.5}),
            ("g width x4", {"alpha_g": (0.25, 0.1)}),
            ("learned alpha_4", {"learn_noise": True}),
            ("80 MAP steps", {"steps": 80}),
        )
    ),
    (
        "process noise 1e-1, g width x2, transition scales",
        {"alpha": (0.9, 0.3, 0.1, 1e-1), "alpha_g": (1.0, 0.1), "scale_transitions": True},
    ),
]


def _fit(obs: torch.Tensor, y: torch.Tensor, cfg: dict[str, Any], seed: int) -> IDDM:
    torch.manual_seed(seed)
    extra = {} if cfg["phase_width"] is None else {"phase_width": cfg["phase_width"]}
    for flag in ("scale_transitions", "learn_noise"):
        if cfg.get(flag):
            extra[flag] = True
    model = cfg["model"](
        list(obs), y, cfg["dx"], intention="continuous", measurement=cfg["kernel"],
        alpha=cfg["alpha"], alpha_g=cfg["alpha_g"], learn_alpha=cfg["learn_alpha"],
        back_constraint=cfg["back_constraint"], init=supervised_init(obs, y, cfg["dx"]), **extra,
    )  # fmt: skip
    with warnings.catch_warnings():  # short fits do not converge; FitResult says so
        warnings.simplefilter("ignore")
        model.fit(cfg["steps"])
    return model


def abs_errors(pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Absolute errors [cm] at the four horizons, ``[n, 4]``."""
    return 100.0 * (pred[:, STEPS] - y[:, None]).abs()


def keep_mask(n: int, held: torch.Tensor) -> torch.Tensor:
    """``[n]`` mask of the strokes outside the held-out fold."""
    keep = torch.ones(n, dtype=torch.bool)
    keep[held] = False
    return keep


def gpr_errors(obs: torch.Tensor, y: torch.Tensor, split, seed: int) -> torch.Tensor:
    """The experiment's GPR (``WindowGPR``) fitted on each fold's training part: its absolute
    errors ``[n, 4]`` on the held-out strokes, in the order of ``split``."""
    errs = []
    for held in split:
        keep = keep_mask(len(y), held)
        model = WindowGPR(windows=(1, 2, 3), seed=seed).fit(list(obs[keep]), y[keep])
        pred = model.predict(obs[held][:, : STEPS[-1] + 1])
        errs.append(abs_errors(pred[0] if isinstance(pred, tuple) else pred, y[held]))
    return torch.cat(errs)


def _sem(v: torch.Tensor) -> float:
    return float(v.std()) / len(v) ** 0.5


def _row(table: ResultTable, name: str, iddm: torch.Tensor, gpr: torch.Tensor, **extra) -> None:
    diff = iddm[:, -1] - gpr[:, -1]
    table.add(
        variant=name,
        **{f"{h} ms": round(float(v), 1) for h, v in zip(HORIZONS_MS, iddm.mean(0), strict=True)},
        **{"ratio to GPR @80 ms": round(float(iddm[:, -1].mean() / gpr[:, -1].mean()), 3)},
        **{"IDDM - GPR @80 ms": f"{float(diff.mean()):+.1f} +- {_sem(diff):.1f}"},
        **extra,
    )  # fmt: skip


def run(quick: bool = False, seed: int = 0, only: str | None = None) -> ResultTable:
    n_train, folds = (16, 2) if quick else (100, 5)
    gen = torch.Generator().manual_seed(seed)  # the experiment's strokes: train first, then test
    strokes = sample_strokes(n_train + (0 if quick else 126), generator=gen)
    obs, y = strokes.obs[:n_train], strokes.targets[:n_train]
    lim = strokes_limit(y)
    grid = torch.linspace(-lim, lim, 13 if quick else 25)
    split = torch.arange(n_train).tensor_split(folds)
    variants = VARIANTS[:1] if quick else VARIANTS
    if only is not None:  # the variants whose name holds this text, and the first (the base)
        variants = [VARIANTS[0], *(v for v in VARIANTS[1:] if only in v[0])]
    base = {**BASE, "steps": 5} if quick else BASE
    table = ResultTable(
        "Target prediction, 5-fold CV on the 100 training strokes: online IDDM variants vs GPR, "
        "MAE [cm]",
        [
            "variant",
            *(f"{h} ms" for h in HORIZONS_MS),
            "ratio to GPR @80 ms",
            "IDDM - GPR @80 ms",
            "T",
            "s",
        ],  # fmt: skip
        meta={
            "seed": seed,
            "n_train": n_train,
            "folds": folds,
            "base": {**base, "features": None, "model": "IDDM"},
        },
    )

    def keep_of(held: torch.Tensor) -> torch.Tensor:
        return keep_mask(n_train, held)

    gpr_err = gpr_errors(obs, y, split, seed)
    _row(table, "GPR (experiment's WindowGPR)", gpr_err, gpr_err)

    for name, change in variants:
        cfg = {**base, **change}
        cols = slice(None) if cfg["features"] is None else cfg["features"]
        start, errs = time.time(), []
        for held in split:
            keep = keep_of(held)
            model = _fit(obs[keep][..., cols], y[keep], cfg, seed)
            mean, _, _ = _online(model, obs[held][:, : STEPS[-1] + 1][..., cols], grid, cfg["eps"])
            errs.append(abs_errors(mean, y[held]))
        _row(table, name, torch.cat(errs), gpr_err, s=round(time.time() - start))

    if only is not None:
        return table
    # the evidence temperature by inner CV, and the evidence of single steps (base model, eps 0)
    start, tempered, temps, single = time.time(), [], [], {t: [] for t in STEPS}
    for held in split:
        keep = keep_of(held)
        inner_logs, inner_truth = [], []
        for inner in torch.nonzero(keep).flatten().tensor_split(2 if quick else 4):
            k2 = keep.clone()
            k2[inner] = False
            model = _fit(obs[k2], y[k2], base, seed)
            _, _, log_prob = _online(model, obs[inner][:, : STEPS[-1] + 1], grid, 0.0)
            inner_logs.append(log_prob[:, STEPS])
            inner_truth.append(grid_index(y[inner], grid)[:, None].expand(-1, len(STEPS)))
        temps.append(fit_temperature(torch.cat(inner_logs), torch.cat(inner_truth)))
        model = _fit(obs[keep], y[keep], base, seed)
        mean, _, _ = _online(model, obs[held][:, : STEPS[-1] + 1], grid, 0.0, temperature=temps[-1])
        tempered.append(abs_errors(mean, y[held]))
        f = OnlineIntentionFilter(model, grid, forgetting=0.0, batch_size=len(held))
        previous = torch.zeros(len(held), len(grid), dtype=obs.dtype)
        for t in range(STEPS[-1] + 1):
            log_belief = f.update(obs[held][:, t]).log_prob
            if t in single:  # this step's evidence alone, on the uniform prior
                evidence = log_belief - previous
                single[t].append((evidence.softmax(-1) * grid).sum(-1))
            previous = log_belief.clone()
    _row(table, "eps 0, T by inner CV", torch.cat(tempered), gpr_err,
         T=", ".join(f"{t:.3g}" for t in temps), s=round(time.time() - start))  # fmt: skip
    for t in STEPS:
        pred = torch.cat(single[t])[:, None].expand(-1, STEPS[-1] + 1)
        err = abs_errors(pred, y)  # the same number in every column: one step's evidence
        table.add(
            variant=f"evidence of step {t} ({HORIZONS_MS[t - 1]} ms) only, eps 0",
            **{"80 ms": round(float(err[:, -1].mean()), 1)},
        )
    return table


def main(argv: list[str]) -> int:
    quick = "--quick" in argv
    only = next((a.split("=", 1)[1] for a in argv if a.startswith("--only=")), None)
    table = run(quick=quick, only=only)
    print(table.to_markdown())
    name = "target_sweep" + ("_quick" if quick else "")
    if only is not None:  # a subset of the rows: its own file
        name += "_" + "".join(c if c.isalnum() else "_" for c in only)
    table.to_json(RESULTS / f"{name}.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
