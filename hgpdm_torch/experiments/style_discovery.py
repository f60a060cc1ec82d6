"""``hgpdm style-discovery``: fit models on styled movements and discover the styles.

Data: synthetic styled movements, or the *Weird Walking* training trials (``--data
weird-walking``: subject 132's 14 walks in four styles, Sec. 2.4.1, standardised). Fits a GPDM
(no style), a supervised H-GPDM (styles given) and an unsupervised H-GPDM whose styles are
discovered by Algorithm 2.1, and as a baseline k-means on summaries of the GPDM's latent
trajectories (mean position and RMS step, :func:`~hgpdm_torch.models.hgpdm.
trajectory_summaries`); prints the style purity and adjusted Rand index against the true styles,
log posterior and fit time of each, and saves a figure of the latent trajectories coloured by
style. On Weird Walking the command first says which trials it found per style, and stops,
naming the absent files, unless all 14 are there.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from sklearn.cluster import KMeans
from sklearn.metrics import adjusted_rand_score

from ..datasets import styled_movements
from ..datasets.cmu import PROTOCOLS, load_protocol
from ..datasets.walkers import MissingTrialsError, Standardizer, find_trials
from ..models import GPDM, HGPDM
from ..models.hgpdm import trajectory_summaries
from ..results import ResultTable
from .arguments import output_folder, positive_int, random_seed, smoke_run

__all__ = ["main", "run_style_discovery", "style_purity"]


def style_purity(truth: torch.Tensor, found: torch.Tensor) -> float:
    """Fraction of sequences whose cluster's majority true style equals their own.

    Args:
        truth: ``[J]`` true style codes.
        found: ``[J]`` discovered codes (any labelling).
    """
    if truth.shape != found.shape or truth.numel() == 0:
        raise ValueError(
            f"truth and found must be equal non-empty [J], got {truth.shape}, {found.shape}"
        )
    total = sum(int(torch.bincount(truth[found == k]).max()) for k in found.unique())
    return total / truth.numel()


def run_style_discovery(
    *,
    data: str = "synthetic",
    folder: str | Path = "../shared/data/cmu",
    num_styles: int = 3,
    per_style: int = 4,
    length: int = 40,
    obs_dim: int = 12,
    latent_dim: int = 3,
    steps: int = 60,
    iterations: int = 6,
    seed: int = 0,
    progress: bool = False,
) -> tuple[ResultTable, dict[str, GPDM]]:
    """Fit GPDM, supervised H-GPDM and discovered H-GPDM on synthetic styles or Weird Walking.

    Args:
        data: ``"synthetic"`` (``num_styles`` x ``per_style`` sequences of ``length`` frames,
            ``obs_dim`` channels) or ``"weird-walking"`` (the protocol's training trials from
            ``folder``; four styles).
        folder: the CMU files (``data="weird-walking"``).
        num_styles: synthetic: the number of styles (Weird Walking has four).
        per_style: synthetic: sequences per style.
        length: synthetic: frames per sequence.
        obs_dim: synthetic: observed channels.
        latent_dim: Dx of every model.
        steps: MAP steps (Alg. 2.1 uses half of them per alternation).
        iterations: alternations of Alg. 2.1.
        seed: seed of the synthetic data, of Alg. 2.1's start and of k-means.
        progress: progress bars.

    Returns:
        The result table and the fitted models by name.

    Raises:
        MissingTrialsError: ``data="weird-walking"`` and some of its 14 training trials are
            not in ``folder`` (all named, before any file is read).
        ValueError: an unknown ``data``.
    """
    if data == "weird-walking":
        spec = PROTOCOLS["weird-walking"]
        find_trials(spec, "train", folder, source=f"folder {folder}").require("all")
        walks = load_protocol(spec, "train", folder, require_all=True)
        std = Standardizer().fit(walks.sequences)
        sequences = [std.transform(s) for s in walks.sequences]
        labels, num_styles = walks.labels, len(walks.label_names)
        title = "Weird Walking training trials (subject 132, four styles)"
    elif data == "synthetic":
        synthetic = styled_movements(num_styles, per_style, length, obs_dim, seed=seed)
        sequences, labels = synthetic.sequences, synthetic.labels
        title = "synthetic styled movements"
    else:
        raise ValueError(f"data must be 'synthetic' or 'weird-walking', got {data!r}")
    table = ResultTable(
        f"hgpdm style-discovery: {title}",
        ["model", "styles", "style purity", "adjusted Rand index", "log posterior", "fit time [s]"],
        meta={"data": data, "num_styles": num_styles, "sequences": len(sequences), "seed": seed},
    )
    if data == "synthetic":
        table.meta |= {"per_style": per_style, "length": length}
    models: dict[str, GPDM] = {}

    start = time.perf_counter()
    gpdm = GPDM(sequences, latent_dim)
    gpdm.fit(steps, progress=progress)
    table.add(
        model="GPDM",
        styles="none",
        **{"log posterior": gpdm.log_posterior(), "fit time [s]": time.perf_counter() - start},
    )
    models["GPDM"] = gpdm
    km = KMeans(num_styles, n_init=10, random_state=seed)
    codes = torch.as_tensor(km.fit_predict(trajectory_summaries(gpdm.latent_sequences())))
    table.add(
        model="k-means on the GPDM's latent trajectories",
        styles="discovered",
        **{
            "style purity": style_purity(labels, codes),
            "adjusted Rand index": adjusted_rand_score(labels.numpy(), codes.numpy()),
        },
    )

    start = time.perf_counter()
    sup = HGPDM(sequences, labels, latent_dim)
    sup.fit(steps, progress=progress)
    table.add(
        model="H-GPDM",
        styles="given",
        **{
            "style purity": 1.0,
            "adjusted Rand index": 1.0,
            "log posterior": sup.log_posterior(),
            "fit time [s]": time.perf_counter() - start,
        },
    )
    models["H-GPDM (given)"] = sup

    start = time.perf_counter()
    found = HGPDM.discover(
        sequences,
        num_styles,
        iterations,
        steps=max(steps // 2, 1),
        latent_dim=latent_dim,
        seed=seed,
        progress=progress,
    )
    table.add(
        model="H-GPDM",
        styles="discovered (Alg. 2.1)",
        **{
            "style purity": style_purity(labels, found.intention_codes()),
            "adjusted Rand index": adjusted_rand_score(
                labels.numpy(), found.intention_codes().cpu().numpy()
            ),
            "log posterior": found.log_posterior(),
            "fit time [s]": time.perf_counter() - start,
        },
    )
    models["H-GPDM (discovered)"] = found
    return table, models


def plot_latents(models: dict[str, GPDM], path: str | Path) -> Path:
    """Save the first two latent dims of each model's trajectories, coloured by style."""
    from matplotlib.figure import Figure  # a bare Figure leaves the pyplot backend alone

    fig = Figure(figsize=(4.2 * len(models), 4))
    axes = fig.subplots(1, len(models), squeeze=False)[0]
    for ax, (name, model) in zip(axes, models.items(), strict=True):
        codes = model.intention_codes() if isinstance(model, HGPDM) else None
        for j, lat in enumerate(model.latent_sequences()):
            color = f"C{int(codes[j])}" if codes is not None else "0.3"
            ax.plot(lat[:, 0], lat[:, 1], color=color, lw=1)
            ax.plot(lat[0, 0], lat[0, 1], "o", color=color, ms=3)
        ax.set(title=name, xlabel="$x_1$", ylabel="$x_2$")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def main(argv: list[str]) -> int:
    """CLI entry: ``hgpdm style-discovery [--data synthetic|weird-walking] [--cmu DIR]
    [--out DIR] [--seed N] [--steps N] [--iterations N] [--quick]``."""
    parser = argparse.ArgumentParser(prog="hgpdm style-discovery", description=__doc__)
    parser.add_argument(
        "--out",
        type=output_folder,
        default="hgpdm_style_discovery_output",
        help="folder for the figure and table",
    )
    parser.add_argument("--data", choices=("synthetic", "weird-walking"), default="synthetic")
    parser.add_argument(
        "--cmu", type=Path, default=Path("../shared/data/cmu"), help="CMU files (weird-walking)"
    )
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument(
        "--steps", type=positive_int, default=None, help="MAP steps (Alg. 2.1: half per round)"
    )
    parser.add_argument("--iterations", type=positive_int, default=None, help="Alg. 2.1 rounds")
    parser.add_argument("--quick", action="store_true", help="smaller problem (also HGPDM_SMOKE=1)")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    if args.data == "weird-walking":
        if not args.cmu.is_dir():
            parser.error(
                f"--cmu {args.cmu} is not a folder (it needs the CMU files; docs, Walking)"
            )
        found = find_trials(
            PROTOCOLS["weird-walking"], "train", args.cmu, source=f"--cmu {args.cmu}"
        )
        try:
            found.require("all")
        except MissingTrialsError as err:
            parser.error(str(err))
        print(f"hgpdm style-discovery: {found.describe()}", file=sys.stderr, flush=True)
    quick = args.quick or smoke_run()
    sizes: dict[str, int] = {"steps": 20, "iterations": 3} if quick else {}
    if quick and args.data == "synthetic":
        sizes |= {"per_style": 3, "length": 25}
    for name in ("steps", "iterations"):
        if getattr(args, name) is not None:
            sizes[name] = getattr(args, name)
    if args.data == "weird-walking":
        torch.set_default_dtype(torch.float64)
    table, models = run_style_discovery(
        data=args.data, folder=args.cmu, seed=args.seed, progress=args.progress, **sizes
    )
    print(table.to_markdown())
    out = Path(args.out)
    table.to_json(out / "style_discovery.json")
    fig = plot_latents(models, out / "latent_trajectories.png")
    print(f"\nsaved {fig} and {out / 'style_discovery.json'}")
    return 0
