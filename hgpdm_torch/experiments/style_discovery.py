"""``hgpdm style-discovery``: fit models on synthetic styled movements and discover the styles.

Fits a GPDM (no style), a supervised H-GPDM (styles given) and an unsupervised H-GPDM whose styles
are discovered by Algorithm 2.1; prints style purity, log posterior and fit time of each, and saves
a figure of the latent trajectories coloured by style.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import torch

from ..datasets import styled_movements
from ..models import GPDM, HGPDM
from .arguments import output_folder, random_seed
from .table import ResultTable

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
    """Fit GPDM, supervised H-GPDM and discovered H-GPDM on synthetic styles.

    Returns:
        The result table and the fitted models by name.
    """
    data = styled_movements(num_styles, per_style, length, obs_dim, seed=seed)
    table = ResultTable(
        "hgpdm style-discovery: synthetic styled movements",
        ["model", "styles", "style purity", "log posterior", "fit time [s]"],
        meta={"num_styles": num_styles, "per_style": per_style, "length": length, "seed": seed},
    )
    models: dict[str, GPDM] = {}

    start = time.perf_counter()
    gpdm = GPDM(data.sequences, latent_dim)
    gpdm.fit(steps, progress=progress)
    table.add(
        model="GPDM",
        styles="none",
        **{"log posterior": gpdm.log_posterior(), "fit time [s]": time.perf_counter() - start},
    )
    models["GPDM"] = gpdm

    start = time.perf_counter()
    sup = HGPDM(data.sequences, data.labels, latent_dim)
    sup.fit(steps, progress=progress)
    table.add(
        model="H-GPDM",
        styles="given",
        **{
            "style purity": 1.0,
            "log posterior": sup.log_posterior(),
            "fit time [s]": time.perf_counter() - start,
        },
    )
    models["H-GPDM (given)"] = sup

    start = time.perf_counter()
    found = HGPDM.discover(
        data.sequences,
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
            "style purity": style_purity(data.labels, found.intention_codes()),
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
    """CLI entry: ``hgpdm style-discovery [--out DIR] [--seed N] [--quick]``."""
    parser = argparse.ArgumentParser(prog="hgpdm style-discovery", description=__doc__)
    parser.add_argument(
        "--out",
        type=output_folder,
        default="hgpdm_style_discovery_output",
        help="folder for the figure and table",
    )
    parser.add_argument("--seed", type=random_seed, default=0)
    parser.add_argument("--quick", action="store_true", help="smaller problem (also HGPDM_SMOKE=1)")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    quick = args.quick or os.environ.get("HGPDM_SMOKE") == "1"
    sizes = {"per_style": 3, "length": 25, "steps": 20, "iterations": 3} if quick else {}
    table, models = run_style_discovery(seed=args.seed, progress=args.progress, **sizes)
    print(table.to_markdown())
    out = Path(args.out)
    table.to_json(out / "style_discovery.json")
    fig = plot_latents(models, out / "latent_trajectories.png")
    print(f"\nsaved {fig} and {out / 'style_discovery.json'}")
    return 0
