"""Runs of ``hgpdm walkers`` side by side (``hgpdm walkers --compare``): one row per run and
window length with its options, the ratio VB H-GPDM / GPDM VB, recognition and the mean RMSE
of the forecasts the H-GPDM must beat."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..results import ResultTable

__all__ = ["COMPARED", "PER_LABEL", "compare_runs"]

#: the rows of :func:`compare_runs`: the best H-GPDM forecast and the baselines it must beat
COMPARED = (
    "VB H-GPDM",
    "GPDM VB",
    "VB H-GPDM + AR(1) residual",
    "GPDM VB + AR(1) residual",
    "ridge AR (CV)",
    "GRU (CV)",
    "repeat last frame",
)
#: the per-label columns of :func:`compare_runs`
PER_LABEL = ("VB H-GPDM + AR(1) residual", "ridge AR (CV)", "GRU (CV)")


def compare_runs(
    tables: list[ResultTable], names: list[str] | list[Path] | None = None
) -> ResultTable:
    """One row per run and window length: its options, the ratio VB H-GPDM / GPDM VB,
    recognition, the mean RMSE (``+- SEM``) of :data:`COMPARED` and, per label, of
    :data:`PER_LABEL`.

    Args:
        tables: tables :func:`walkers` wrote for one protocol and evaluation (e.g. CV runs with
            different options).
        names: how errors name each table (e.g. its file; default ``tables[i]``).

    Raises:
        ValueError: no table, or a table that :func:`walkers` did not write (its ``meta``
            lacks the run's settings or summary).
    """
    if not tables:
        raise ValueError("tables must hold at least one walkers table")
    keys = ("protocol", "evaluation", "summary", "model_options")  # what a run wrote
    for i, table in enumerate(tables):
        if lacks := [k for k in keys if k not in table.meta]:
            raise ValueError(
                f"{names[i] if names else f'tables[{i}]'}: not a table of hgpdm walkers (its "
                f"meta lacks {lacks}); compare the --out tables of hgpdm walkers runs"
            )
    labels = sorted(
        {lab for t in tables for s in t.meta["summary"].values() for lab in s["per label"]}
    )
    columns = ["options", "T", "VB H-GPDM / GPDM VB", "accuracy", "90% set coverage",
               "ProMP accuracy"]  # fmt: skip
    columns += [*COMPARED, *(f"{m} ({lab})" for m in PER_LABEL for lab in labels)]
    first = tables[0].meta
    out = ResultTable(
        f"{first['protocol']} ({first['evaluation']}): runs compared, mean RMSE over trials",
        columns,
        meta={"protocol": first["protocol"], "evaluation": first["evaluation"]},
    )
    for table in tables:
        meta = table.meta
        opts = meta["model_options"]
        parts = [f"Dx {meta['latent_dim']}", f"{meta['fit_steps']} MAP steps"]
        parts.append(f"sharing {meta['sharing']}")
        if "back_constraint" in opts:
            parts.append(f"{opts['back_constraint']} back-constraint")
        learned = opts.get("learn_measurement_width", "True") == "True"
        parts.append("learned measurement width" if learned else "fixed measurement width")
        if opts.get("learn_noise") == "True":
            parts.append("learned alpha_4")
        if meta.get("noise_per_label"):
            parts.append("alpha_4 per label")
        if meta.get("features", "frames") != "frames":
            parts.append(f"{meta['features']} features")
        name = ", ".join(parts)
        if meta.get("measurement_points"):
            name += f", measurement_points {meta['measurement_points']}"
        for T, summary in meta["summary"].items():
            rows = {r["trial"]: r for r in table.rows if str(r["T"]) == T}
            cells: dict[str, Any] = {"options": name, "T": int(T)}
            cells["VB H-GPDM / GPDM VB"] = summary["VB H-GPDM / GPDM VB"]
            cells["accuracy"] = rows["average"]["accuracy"]
            cells["90% set coverage"] = rows["average"]["90% set coverage"]
            cells["ProMP accuracy"] = rows["average"].get("ProMP accuracy")  # older runs: none
            for m in COMPARED:
                cells[m] = f"{rows['average'][m]:.3f} +- {rows['SEM'][m]:.3f}"
            for m in PER_LABEL:
                for lab in labels:
                    cells[f"{m} ({lab})"] = summary["per label"].get(lab, {}).get(m)
            out.add(**cells)
    return out
