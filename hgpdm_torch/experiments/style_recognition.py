"""Style recognition, forecasting and gap recovery with VB in the H-GPDM (thesis Sec. 2.4,
Tables 2.1-2.4, Fig. 2.3).

Protocol (Tables 2.1-2.4): a model is fitted to training sequences; every test sequence is cut
into sliding windows ``z_{i:i+T}`` (T = 5 and 10) and each method forecasts ``z_{i+T}``. Columns:

- VB H-GPDM: Algorithm 2.2 over all styles (forecast RMSE, and recognition accuracy of the ML
  style);
- oracle H-GPDM: the true style given, VB and MAP (conditional GPDM) inference;
- GPDM: one model without g, VB and MAP;
- baselines: repeat the last frame; ridge AR(k), k and ridge strength by CV grouped by training
  sequence.

Data sets: (a) synthetic styled movements (:func:`~hgpdm_torch.datasets.styled_movements`, a
held-out split of one generated set) and (b) aeon's BasicMotions (smartwatch accelerometer and
gyroscope, Dz = 6, activity as g; ``aeon`` is an optional extra). RMSE is in observation units
(BasicMotions: channels standardised with the training statistics).

:func:`gap_recovery_figure` draws Fig. 2.3's comparison: a window with missing frames recovered
by the H-GPDM and the GPDM (joint q(z) conditioned on the observed rows, App. 2.B).

Sizes shrink under ``HGPDM_SMOKE=1``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from matplotlib.figure import Figure

from ..baselines import LastFrameForecaster, RidgeAR
from ..datasets import styled_movements
from ..inference.map import MAPInference
from ..inference.variational import VariationalInference
from ..models import GPDM, HGPDM
from ..progress import tqdm
from ..results import ResultTable
from ..validation import check_choice
from .arguments import SMOKE, output_file, positive_int, random_seed

__all__ = [
    "StyleData",
    "chunked_forecast",
    "chunked_windows",
    "forecast_windows",
    "gap_recovery_figure",
    "load_data",
    "main",
    "sequence_length",
    "style_recognition",
]

DATASETS = ("synthetic", "basic_motions")
COLUMNS = [
    "data",
    "T",
    "windows",
    "VB H-GPDM RMSE",
    "VB H-GPDM accuracy",
    "oracle VB RMSE",
    "oracle MAP RMSE",
    "GPDM VB RMSE",
    "GPDM MAP RMSE",
    "repeat last frame RMSE",
    "ridge AR (CV) RMSE",
    "VB ms/window",
]
#: BasicMotions recordings: 100 frames, of which every _BASIC_MOTIONS_STEP-th is kept.
_BASIC_MOTIONS_FRAMES, _BASIC_MOTIONS_STEP = 100, 3
# numbers a chunk of windows may hold in its largest temporaries (160 MB in float64)
_MAX_ENTRIES = 2e7


@dataclass
class StyleData:
    """Training sequences with style codes and held-out test sequences."""

    name: str
    train: list[torch.Tensor]
    train_labels: torch.Tensor
    test: list[torch.Tensor]
    test_labels: torch.Tensor


def sequence_length(name: str, *, smoke: bool = SMOKE) -> int:
    """Frames per sequence of the data set ``name`` as :func:`load_data` returns it; a forecast
    window (:func:`forecast_windows`) must be shorter."""
    check_choice(name, "name", DATASETS)
    if name == "synthetic":
        return 30 if smoke else 40
    return -(-_BASIC_MOTIONS_FRAMES // _BASIC_MOTIONS_STEP)


def load_data(name: str, *, seed: int = 0, smoke: bool = SMOKE) -> StyleData:
    """The synthetic set or BasicMotions (needs ``aeon``), at smoke or full size.

    BasicMotions is subsampled to every 3rd frame (34 frames); a few recordings per activity are
    used for training (the GP's N grows with every frame), all channels standardised.
    """
    check_choice(name, "name", DATASETS)
    if name == "synthetic":
        length = sequence_length(name, smoke=smoke)
        train, test = styled_movements(3, 4, length, 12, seed=seed).split(0.25, seed)
        return StyleData(name, train.sequences, train.labels, test.sequences, test.labels)
    try:
        from aeon.datasets import load_basic_motions
    except ImportError as err:  # optional extra
        raise ImportError("the BasicMotions data set needs the optional package aeon") from err
    n_train, n_test = (2, 1) if smoke else (3, 4)
    parts = []
    for split, n in (("train", n_train), ("test", n_test)):
        x, y = load_basic_motions(split=split)
        names = sorted(set(y))
        codes = torch.tensor([names.index(v) for v in y])
        keep = torch.cat([torch.nonzero(codes == k).flatten()[:n] for k in range(len(names))])
        z = torch.as_tensor(x, dtype=torch.float64).transpose(1, 2)[keep, ::_BASIC_MOTIONS_STEP]
        parts.append((z, codes[keep]))
    (ztr, ytr), (zte, yte) = parts
    mean, std = ztr.reshape(-1, ztr.shape[-1]).mean(0), ztr.reshape(-1, ztr.shape[-1]).std(0)
    return StyleData(name, list((ztr - mean) / std), ytr, list((zte - mean) / std), yte)


def forecast_windows(
    sequences: list[torch.Tensor], labels: Any, length: int, stride: int
) -> tuple[torch.Tensor, ...]:
    """Windows ``[W, T, Dz]`` of ``length`` frames every ``stride`` frames, each window's next
    frame ``[W, Dz]`` and its sequence's style code ``[W]``."""
    z, nxt, y = [], [], []
    for seq, label in zip(sequences, labels, strict=True):
        for i in range(0, seq.shape[0] - length, stride):
            z.append(seq[i : i + length])
            nxt.append(seq[i + length])
            y.append(int(label))
    return torch.stack(z), torch.stack(nxt), torch.tensor(y)


def chunked_windows(
    fn: Callable[..., Any], z: torch.Tensor, per_window: float, **kw: object
) -> list:
    """Run ``fn`` on chunks of the windows ``z [W, ...]`` (and of every tensor in ``kw``) so
    that a chunk holds at most ``2e7`` numbers when one window needs ``per_window``; returns
    the outputs per chunk, in order."""
    size = max(1, int(_MAX_ENTRIES // max(per_window, 1.0)))
    outs = []
    for i in range(0, z.shape[0], size):
        sub = {k: (v[i : i + size] if torch.is_tensor(v) else v) for k, v in kw.items()}
        outs.append(fn(z[i : i + size], **sub))
    return outs


def window_entries(inf: Any, candidates: int, length: int) -> int:
    """Numbers in the largest temporaries of one window's inference and forecast: the joint
    ``q(z_{1:T+1})`` of App. 2.B per candidate g, ``K ((T + 1) Dz)^2`` (the kernel
    expectations are computed in cache-sized chunks of input Gaussians)."""
    return candidates * ((length + 1) * inf.obs_dim) ** 2


def chunked_forecast(
    inf: VariationalInference,
    z: torch.Tensor,
    values: torch.Tensor | None = None,
    residual: str | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:meth:`VariationalInference.forecast` over windows ``z [W, T, Dz]`` in memory-bounded
    chunks. ``values``: ``[W, 1]`` given g per window (oracle), or ``None`` to infer it;
    ``residual``: see :meth:`VariationalInference.forecast`.

    Returns:
        ``mean [W, Dz]`` of the next frame, ``g_ml [W]`` (index into ``inf.values``) and the
        posterior over g ``[W, K]``.
    """
    K = 1 if values is not None or inf.kind != "discrete" else int(inf.values.numel())
    per_window = window_entries(inf, K, z.shape[-2])
    kw = {} if values is None else {"values": values}
    outs = chunked_windows(
        lambda w, **k: inf.forecast(w, residual=residual, **k), z, per_window, **kw
    )
    mean = torch.cat([o[0] for o in outs])
    g_ml = torch.cat([o[2].g_ml for o in outs])
    return mean, g_ml, torch.cat([o[2].posterior for o in outs])


def style_recognition(
    datasets: tuple[str, ...] = DATASETS,
    *,
    lengths: tuple[int, ...] = (5, 10),
    latent_dim: int = 3,
    fit_steps: int = 60,
    stride: int | None = None,
    seed: int = 0,
    progress: bool = False,
) -> ResultTable:
    """Tables 2.1-2.4: forecast RMSE and recognition accuracy per data set and window length.

    Args:
        datasets: any of ``"synthetic"``, ``"basic_motions"`` (skipped with a note in
            ``meta["skipped"]`` when ``aeon`` is missing).
        lengths: window lengths T.
        latent_dim: Dx of all models.
        fit_steps: L-BFGS steps of the MAP fits.
        stride: step between windows (default 4, smoke 6).
        seed: data seed.
        progress: show a progress bar over data sets and lengths.

    Returns:
        A :class:`ResultTable` with columns :data:`COLUMNS`.

    Raises:
        ValueError: an unknown data set, a size that is not a positive int, or a window length
            not shorter than the data set's sequences (checked before any fit).
    """
    for name in datasets:
        check_choice(name, "datasets", DATASETS)
    if isinstance(lengths, int) or not lengths:
        raise ValueError(f"lengths must be a non-empty tuple of positive ints, got {lengths!r}")
    for name, value in (
        *(("lengths", T) for T in lengths),
        ("latent_dim", latent_dim),
        ("fit_steps", fit_steps),
        ("stride", 1 if stride is None else stride),
    ):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    stride = stride or (6 if SMOKE else 4)
    table = ResultTable(
        "Tables 2.1-2.4: next-frame forecast RMSE and style recognition accuracy",
        list(COLUMNS),
        meta={"latent_dim": latent_dim, "fit_steps": fit_steps, "stride": stride, "seed": seed},
    )
    jobs = [(d, T) for d in datasets for T in lengths]
    models: dict[str, tuple] = {}
    for name, T in tqdm(jobs, disable=not progress, desc="style recognition"):
        if name not in models:
            try:
                data = load_data(name, seed=seed)
            except ImportError as err:
                table.meta.setdefault("skipped", {})[name] = str(err)
                models[name] = None
                continue
            shortest = min(s.shape[0] for s in data.test)
            if max(lengths) >= shortest:
                raise ValueError(
                    f"lengths must be below the {name} test sequences' {shortest} frames, "
                    f"got {max(lengths)}"
                )
            hg = HGPDM(data.train, data.train_labels, latent_dim)
            gp = GPDM(data.train, latent_dim)
            for label, model in (("H-GPDM", hg), ("GPDM", gp)):
                fits = table.meta.setdefault("fits", {})
                fits[f"{name} {label}"] = model.fit(fit_steps).summary()
            models[name] = (data, hg, gp)
        if models[name] is None:
            continue
        data, hg, gp = models[name]
        z, nxt, y = forecast_windows(data.test, data.test_labels, T, stride)

        def rmse(mean: torch.Tensor, nxt: torch.Tensor = nxt) -> float:
            return float((mean - nxt).pow(2).mean().sqrt())

        vb = VariationalInference(hg)
        start = time.perf_counter()
        mean, g_ml, _ = chunked_forecast(vb, z)
        ms = 1e3 * (time.perf_counter() - start) / z.shape[0]
        oracle = y[:, None]
        table.add(
            **{
                "data": name,
                "T": T,
                "windows": int(z.shape[0]),
                "VB H-GPDM RMSE": rmse(mean),
                "VB H-GPDM accuracy": float((vb.values[g_ml] == y).double().mean()),
                "oracle VB RMSE": rmse(chunked_forecast(vb, z, oracle)[0]),
                "oracle MAP RMSE": rmse(chunked_forecast(MAPInference(hg), z, oracle)[0]),
                "GPDM VB RMSE": rmse(chunked_forecast(VariationalInference(gp), z)[0]),
                "GPDM MAP RMSE": rmse(chunked_forecast(MAPInference(gp), z)[0]),
                "repeat last frame RMSE": rmse(LastFrameForecaster().fit(data.train).predict(z)),
                "ridge AR (CV) RMSE": rmse(RidgeAR().fit(data.train).predict(z)),
                "VB ms/window": ms,
            }
        )
    return table


def gap_recovery_figure(
    path: str | Path,
    *,
    length: int = 12,
    gap: tuple[int, int] = (4, 8),
    latent_dim: int = 3,
    fit_steps: int = 60,
    seed: int = 3,
) -> dict[str, float]:
    """Fig. 2.3: recover missing frames of two-style movements with the H-GPDM and the GPDM.

    Fits both models to a two-style synthetic set, removes frames ``gap[0]:gap[1]`` from every
    test window and recovers them by conditioning the joint q(z) (App. 2.B). Saves a figure of
    one window (two observed channels, truth and both recoveries with 2-sd bands) to ``path``.

    Returns:
        The recovery RMSE over all test windows, per model (``{"H-GPDM": ..., "GPDM": ...}``).
    """
    train, test = styled_movements(2, 4, 30, 12, seed=seed).split(0.25, seed=0)
    z = torch.stack([s[i : i + length] for s in test.sequences for i in range(0, 30 - length, 4)])
    holed = z.clone()
    holed[:, gap[0] : gap[1]] = float("nan")
    out, rmse = {}, {}
    for name, model in (
        ("H-GPDM", HGPDM(train.sequences, train.labels, latent_dim)),
        ("GPDM", GPDM(train.sequences, latent_dim)),
    ):
        model.fit(fit_steps)
        vb = VariationalInference(model)
        rec, var = vb.predict_observations(holed, vb.infer(holed))
        out[name] = (rec, var)
        err = rec[:, gap[0] : gap[1]] - z[:, gap[0] : gap[1]]
        rmse[name] = float(err.pow(2).mean().sqrt())
    # a bare Figure draws with Agg on savefig and leaves the user's pyplot backend alone
    fig = Figure(figsize=(9, 3.2))
    axes = fig.subplots(1, 2, sharex=True)
    t = torch.arange(length)
    for ax, ch in zip(axes, (0, 1), strict=True):
        ax.plot(t, z[0, :, ch], "k.-", label="truth")
        ax.axvspan(gap[0] - 0.5, gap[1] - 0.5, color="0.9", label="missing")
        for (name, (rec, var)), color in zip(out.items(), ("C0", "C3"), strict=True):
            sd = var[0, :, ch].sqrt()
            ax.plot(t, rec[0, :, ch], color=color, label=f"{name} ({rmse[name]:.3f})")
            ax.fill_between(t, rec[0, :, ch] - 2 * sd, rec[0, :, ch] + 2 * sd, color=color,
                            alpha=0.2)  # fmt: skip
        ax.set_title(f"channel {ch}")
        ax.set_xlabel("frame")
    axes[0].legend(fontsize=7)
    fig.suptitle("Gap recovery (VB, joint q(z)); legend: RMSE over all test windows")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return rmse


def main(argv: list[str]) -> int:
    """``hgpdm style-recognition [--data synthetic basic_motions] [--lengths 5 10]
    [--out table.json] [--figure gap.png]``."""
    parser = argparse.ArgumentParser(prog="hgpdm style-recognition", description=__doc__)
    parser.add_argument("--data", nargs="+", default=list(DATASETS), choices=DATASETS)
    parser.add_argument("--lengths", nargs="+", type=positive_int, default=[5, 10])
    parser.add_argument("--fit-steps", type=positive_int, default=60)
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--out", type=output_file, default=None, help="write the table as JSON")
    parser.add_argument(
        "--figure", type=output_file, default=None, help="gap-recovery figure (PNG)"
    )
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    for name in args.data:
        frames = sequence_length(name)
        if max(args.lengths) >= frames:
            parser.error(
                f"argument --lengths: windows must be shorter than the {name} sequences "
                f"({frames} frames), got {max(args.lengths)}"
            )
    torch.set_default_dtype(torch.float64)
    table = style_recognition(
        tuple(args.data),
        lengths=tuple(args.lengths),
        fit_steps=args.fit_steps,
        seed=args.seed,
        progress=args.progress,
    )
    print(table.to_markdown())
    if args.out is not None:
        table.to_json(args.out)
    if args.figure is not None:
        print("gap recovery RMSE:", gap_recovery_figure(args.figure, fit_steps=args.fit_steps))
    return 0
