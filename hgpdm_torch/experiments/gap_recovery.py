"""Recovery of missing frames on the *Four Walkers* protocol (thesis Sec. 2.4.1, Table 2.5).

Protocol (:data:`~hgpdm_torch.datasets.cmu.PROTOCOLS` ``four-walkers``, after Wang et al. 2008):
models fitted on one walk per subject (35_02, 10_04, 12_01, 16_05; g = subject), all trials
down-sampled by four (30 frames/s), Taylor-style features standardised with training
statistics. From each test trial (35_03, 12_02, 12_03, 16_21) the first 50 frames are taken and
31 consecutive frames removed, at the 12 placements 5-35, 6-36, ..., 16-46 (frames counted from
1); every method recovers them:

- ``VB H-GPDM``: Algorithm 2.2 on the 50-frame window with missing rows, the joint ``q(z)`` of
  the ML subject conditioned on the observed rows (App. 2.B); ``(BMA)``: averaged over subjects
  under the posterior; ``oracle VB``: the true subject's;
- ``oracle MAP`` (conditional GPDM: GP mean at the MAP states of the true subject), ``GPDM VB``,
  ``GPDM MAP``;
- baselines: ``linear interpolation`` between the frames either side of the gap, and
  ``template copy``: the 50-frame stretch of a training trial closest (least squares) to the
  observed frames, its frames copied into the gap.

RMSE is over the missing frames and all standardised channels of a trial's 12 placements; a
subject with no training trial here can be tested (VB picks among the known subjects) but has no
oracle rows. The test trials found in ``test_folder`` are scored (absent ones listed), and none
from elsewhere; without ``test_folder`` they are looked for in ``folder``: 35_03 is among the
training data of ``../shared/data/cmu``, so the default finds one. Before any work the command
says which trials it found where, per subject, and stops, naming the files, when it has no
training trial or no test trial.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..datasets.cmu import PROTOCOLS, load_protocol, load_trials
from ..datasets.walkers import FoundTrials, MissingTrialsError, Standardizer, find_trials
from ..inference.map import MAPInference
from ..inference.variational import VariationalInference
from ..inference.variational.prediction import candidate_predictions
from ..models import GPDM, HGPDM
from ..results import ResultTable
from .arguments import SMOKE, output_file, positive_int
from .intervals import mean_sem
from .walkers import DEFAULT_OPTIONS, MODEL_METHODS, report

__all__ = [
    "METHODS",
    "four_walkers_trials",
    "gap_recovery",
    "linear_interpolation",
    "main",
    "template_copy",
]

METHODS = (*MODEL_METHODS, "linear interpolation", "template copy")
#: the thesis's windows: 50 frames, 31 missing, first missing frame 5 ... 16 (1-based)
FRAMES, GAP, FIRST_GAPS = 50, 31, tuple(range(4, 16))


def linear_interpolation(z: torch.Tensor) -> torch.Tensor:
    """Fill the missing (NaN) rows of windows ``[W, T, Dz]`` linearly between the observed rows
    either side (the first / last observed row where the gap touches an end)."""
    out = z.clone()
    observed = ~torch.isnan(z).any(-1)
    for w in range(z.shape[0]):
        seen = torch.nonzero(observed[w]).flatten().numpy()
        if seen.size == 0:
            raise ValueError(f"window {w} has no observed row")
        t = np.arange(z.shape[1])
        for d in range(z.shape[2]):
            out[w, :, d] = torch.as_tensor(np.interp(t, seen, z[w, seen, d].numpy())).to(z)
    return out


def template_copy(z: torch.Tensor, train: list[torch.Tensor]) -> torch.Tensor:
    """Fill the missing rows of windows ``[W, T, Dz]`` from the closest stretch of ``T`` training
    frames: the one with the least squared distance over the observed rows."""
    parts = [s.unfold(0, z.shape[1], 1).transpose(1, 2) for s in train if s.shape[0] >= z.shape[1]]
    if not parts:
        raise ValueError(f"train: no training sequence has {z.shape[1]} frames")
    stretches = torch.cat(parts)  # [S, T, Dz]
    observed = ~torch.isnan(z).any(-1)  # [W, T]
    diff = torch.nan_to_num(z)[:, None] - stretches[None]  # [W, S, T, Dz]
    cost = (diff.pow(2).sum(-1) * observed[:, None]).sum(-1)
    best = stretches[cost.argmin(1)]
    return torch.where(observed[..., None], z, best)


def four_walkers_trials(
    folder: str | Path,
    test_folder: str | Path | None = None,
    names: tuple[str, str] = ("folder", "test_folder"),
) -> tuple[FoundTrials, FoundTrials]:
    """Which Four Walkers training trials ``folder`` holds and which test trials
    ``test_folder`` holds (their skeletons may lie in ``folder``), or ``folder`` when no
    ``test_folder`` is given; messages name the folders by ``names``.

    Raises:
        MissingTrialsError: no training trial, or no test trial where they are looked for
            (a subject without a training trial is allowed: it has no oracle rows).
        FileNotFoundError: a folder that does not exist.
    """
    spec = PROTOCOLS["four-walkers"]
    train = find_trials(spec, "train", folder, source=f"{names[0]} {folder}")
    train.require("any")
    where = test_folder if test_folder is not None else folder
    source = f"{names[1]} {test_folder}"
    if test_folder is None:
        source = f"{names[0]} {folder} (no {names[1]} given)"
    test = find_trials(spec, "test", where, skeletons=[folder], source=source)
    test.require("any")
    return train, test


def gap_recovery(
    *,
    folder: str | Path = "../shared/data/cmu",
    test_folder: str | Path | None = None,
    latent_dim: int = 3,
    fit_steps: int = 300,
    gaps: tuple[int, ...] = FIRST_GAPS,
    model_options: dict[str, Any] | None = None,
) -> ResultTable:
    """Table 2.5 on the Four Walkers trials that are present (see the module docstring).

    Args:
        folder: the training trials' folder.
        test_folder: the test trials' folder, the only place they are taken from (their
            skeletons may come from ``folder``); ``None``: ``folder``.
        latent_dim: Dx of both models.
        fit_steps: maximum MAP steps per fit.
        gaps: first missing frame of each placement (0-based; the thesis's 4 ... 15).
        model_options: constructor arguments of both models, over the Walkers defaults
            (:data:`~hgpdm_torch.experiments.walkers.DEFAULT_OPTIONS`: with one training trial
            per subject, Four Walkers allows no leave-one-trial-out choice of its own).

    Returns:
        A :class:`ResultTable`: one row per test trial, an ``average`` row (mean over trials)
        and, with several trials, a ``SEM`` row; ``meta`` lists the trials used and missing,
        and the fits.

    Raises:
        MissingTrialsError: no training trial or no test trial (:func:`four_walkers_trials`),
            before any file is read.
        ValueError: bad ``gaps``, or a test trial shorter than 50 frames.
    """
    if any(g < 0 or g + GAP > FRAMES for g in gaps):
        raise ValueError(f"gaps must lie in [0, {FRAMES - GAP}], got {gaps}")
    spec = PROTOCOLS["four-walkers"]
    _, found = four_walkers_trials(folder, test_folder)
    data = load_protocol(spec, "train", folder)
    # the test motions from where they were found only, their skeletons also from folder
    where = test_folder if test_folder is not None else folder
    test = load_trials(
        found.found, [where, folder], downsample=spec.downsample, label_names=spec.label_names
    )
    short = [t for t, s in zip(test.trials, test.sequences, strict=True) if s.shape[0] < FRAMES]
    if short:
        raise ValueError(f"test trials {short} have fewer than {FRAMES} frames")
    options = DEFAULT_OPTIONS["walkers"] | dict(model_options or {})
    # the models know only the subjects with a training trial here
    present = sorted(set(data.labels.tolist()))
    std = Standardizer().fit(data.sequences)
    tr = [std.transform(s) for s in data.sequences]
    start = time.perf_counter()
    hg = HGPDM(tr, data.labels, latent_dim, **options)
    gp = GPDM(tr, latent_dim, **options)
    fits: dict[str, Any] = {
        n: m.fit(fit_steps).summary() for n, m in (("H-GPDM", hg), ("GPDM", gp))
    }
    fits["seconds"] = time.perf_counter() - start
    vb_hg, vb_gp = VariationalInference(hg), VariationalInference(gp)
    map_hg, map_gp = MAPInference(hg), MAPInference(gp)
    table = ResultTable(
        "four-walkers (Table 2.5): RMSE of the recovered frames (standardised)",
        ["trial", "label", *METHODS, "accuracy"],
        meta={
            "training trials": data.trials,
            "missing training trials": data.missing,
            "test trials": test.trials,
            "missing test trials": found.missing_trials,
            "test trials from": found.source,
            "fps": data.fps,
            "latent_dim": latent_dim,
            "fit_steps": fit_steps,
            "model_options": {k: str(v) for k, v in options.items()},
            "gaps (0-based first missing frame)": list(gaps),
            "fits": fits,
        },
    )
    per: dict[str, list[float]] = {m: [] for m in (*METHODS, "accuracy")}
    for j, seq in enumerate(test.sequences):
        z = std.transform(seq[:FRAMES]).expand(len(gaps), FRAMES, -1).clone()
        holed = z.clone()
        missing = torch.zeros(len(gaps), FRAMES, dtype=torch.bool)
        for i, g in enumerate(gaps):
            missing[i, g : g + GAP] = True
        holed[missing] = float("nan")
        label = int(test.labels[j])
        known = label in present
        k = int((vb_hg.values == label).nonzero()[0, 0]) if known else None
        parts: dict[str, list[torch.Tensor]] = {}
        correct = []
        # one placement at a time: the joint q(z) of a 50-frame window is [T Dz, T Dz] per g
        for w in range(len(gaps)):
            one = holed[w : w + 1]
            res = vb_hg.infer(one, prune=None)
            cand, _ = candidate_predictions(vb_hg, one, res)  # [1, K, T, Dz]
            recs = {
                "VB H-GPDM": cand[:, res.g_ml[0]],
                "VB H-GPDM (BMA)": (res.posterior[..., None, None] * cand).sum(1),
                "GPDM VB": vb_gp.predict_observations(one, vb_gp.infer(one))[0],
                "GPDM MAP": map_gp.predict_observations(one, map_gp.infer(one))[0],
            }
            if known:
                recs["oracle VB"] = cand[:, k]
                val = torch.full((1, 1), label)
                recs["oracle MAP"] = map_hg.predict_observations(
                    one, map_hg.infer(one, values=val)
                )[0]
                correct.append(int(vb_hg.values[res.g_ml[0]]) == label)
            for name, value in recs.items():
                parts.setdefault(name, []).append(value)
        recs = {name: torch.cat(values) for name, values in parts.items()}
        recs["linear interpolation"] = linear_interpolation(holed)
        recs["template copy"] = template_copy(holed, tr)
        row: dict[str, Any] = {"trial": test.trials[j], "label": test.label_names[label]}
        for m in METHODS:
            row[m] = float((recs[m] - z)[missing].pow(2).mean().sqrt()) if m in recs else None
        row["accuracy"] = sum(correct) / len(correct) if known else None
        table.add(**row)
        for key in per:
            if row[key] is not None:
                per[key].append(row[key])
    cells: dict[str, Any] = {"trial": "average", "label": "all"}
    sem: dict[str, Any] = {"trial": "SEM", "label": "all"}
    for key, values in per.items():
        if values:
            cells[key], spread = mean_sem(values)
            if key in METHODS and spread is not None:
                sem[key] = spread
    table.add(**cells)
    if len(sem) > 2:
        table.add(**sem)
    return table


def main(argv: list[str]) -> int:
    """``hgpdm gap-recovery [--data DIR] [--test-data DIR] [--latent-dim 3] [--fit-steps 300]
    [--out table.json]``."""
    parser = argparse.ArgumentParser(prog="hgpdm gap-recovery", description=__doc__)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/cmu"))
    parser.add_argument(
        "--test-data",
        type=Path,
        default=None,
        help="the test trials' folder (default: --data); a folder given must hold one",
    )
    parser.add_argument("--latent-dim", type=positive_int, default=3)
    parser.add_argument("--fit-steps", type=positive_int, default=40 if SMOKE else 300)
    parser.add_argument("--out", type=output_file, default=None, help="write the table as JSON")
    args = parser.parse_args(argv)
    for name, path in (("--data", args.data), ("--test-data", args.test_data)):
        if path is not None and not path.is_dir():
            parser.error(f"{name} {path} is not a folder (it needs the CMU files; docs, Walking)")
    try:
        found = four_walkers_trials(args.data, args.test_data, ("--data", "--test-data"))
    except MissingTrialsError as err:
        parser.error(str(err))
    for part in found:
        print(f"hgpdm gap-recovery: {part.describe()}", file=sys.stderr, flush=True)
    torch.set_default_dtype(torch.float64)
    table = gap_recovery(
        folder=args.data,
        test_folder=args.test_data,
        latent_dim=args.latent_dim,
        fit_steps=args.fit_steps,
    )
    report(table, args.out)
    return 0
