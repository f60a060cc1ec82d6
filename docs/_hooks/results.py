"""MkDocs hook: result tables rendered from the JSON files the commands write.

A page line ``<!-- results: gpu-check -->`` becomes the latest accelerator check
(``benchmarks/results/gpu_check.json``, written by ``make gpu-check``) and the benchmark tables
it names; ``<!-- results: table PATH -->`` becomes the table of the JSON file ``PATH`` (relative
to the repository root) that a command wrote, with the settings in its meta;
``<!-- results: demo-seeds GLOB -->`` one row per ``hgpdm demo`` file matching ``GLOB`` (its
return rates and paired differences); ``<!-- results: meta-table PATH#KEY -->`` the list of
records under ``KEY`` in the meta of ``PATH``. Each table goes through
:meth:`hgpdm_torch.results.ResultTable.to_markdown`, so the page shows what the files
hold and never a copy typed by hand. A missing file is a warning (the strict build fails).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any

from hgpdm_torch.results import ResultTable

log = logging.getLogger("mkdocs.hooks.results")

_MARKER = re.compile(r"^<!-- results: ([\w-]+)(?: ([\w./*#-]+))? -->$", re.MULTILINE)


def _gpu_check(root: Path) -> str:
    path = root / "benchmarks" / "results" / "gpu_check.json"
    if not path.exists():
        log.warning(f"{path} is missing: run `make gpu-check` on a machine with CUDA")
        return "*No accelerator check recorded yet.*"
    summary = json.loads(path.read_text())
    meta = summary["meta"]
    facts = ", ".join(f"{k} {v}" for k, v in meta.items() if k not in ("device", "cuda"))
    lines = [f"Device: **{meta['device']}** ({facts}).", "",
             "| step | status | wall [s] | date |", "|---|---|---|---|"]  # fmt: skip
    for step in summary["steps"]:
        counts = step.get("counts")
        status = step["status"] + (f" ({counts})" if counts else "")
        lines.append(f"| {step['step']} | {status} | {step.get('seconds', '')} | "
                     f"{step.get('date', '')} |")  # fmt: skip
    for step in summary["steps"]:
        table = step.get("results")
        if table and (root / table).exists():
            lines += ["", ResultTable.from_json(root / table).to_markdown(".3g"), "",
                      f"*Source: `{table}`.*"]  # fmt: skip
        elif table:
            log.warning(f"{table}, named by {path.name}, is missing")
    return "\n".join(lines)


def _table(root: Path, name: str | None) -> str:
    """A command's result table (``ResultTable.to_json``) and the scalar settings of its meta."""
    path = root / (name or "")
    if not name or not path.is_file():
        log.warning(f"results table {name!r} is missing")
        return f"*Missing result file `{name}`.*"
    table = ResultTable.from_json(path)
    facts = [f"{k}: {v:.4g}" if isinstance(v, float) else f"{k}: {v}"
             for k, v in table.meta.items() if isinstance(v, str | int | float)]  # fmt: skip
    return "\n".join([table.to_markdown(".3g"), "", f"*Source: `{name}`; " + "; ".join(facts)
                      + ".*"])  # fmt: skip


def _meta_table(root: Path, arg: str | None) -> str:
    """``PATH#KEY``: the list of records under ``KEY`` in the meta of the JSON file ``PATH`` (e.g.
    a benchmark's per-executor timings), one row per record, numbers to 3 significant digits."""
    name, _, key = (arg or "").partition("#")
    path = root / name
    records = ResultTable.from_json(path).meta.get(key) if name and path.is_file() else None
    if not isinstance(records, list) or not records or not isinstance(records[0], dict):
        log.warning(f"meta-table: {name!r} has no list of records under {key!r} in its meta")
        return f"*Missing `{key}` in the meta of `{name}`.*"
    head = list(records[0])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for record in records:
        cells = (f"{v:.3g}" if isinstance(v, float) else str(v) for v in record.values())
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join([*lines, "", f"*Source: `{name}`, meta `{key}`.*"])


#: the players of :func:`_demo_seeds`' columns, and the paired differences it shows
_DEMO_PLAYERS = ("best blind (training folds)", "best fixed time (training folds)", "LSPI", "MCP")
_DEMO_DIFFERENCES = ("MCP - best fixed time (training folds)",
                     "LSPI - best fixed time (training folds)")  # fmt: skip


def _demo_seeds(root: Path, pattern: str | None) -> str:
    """One row per ``hgpdm demo`` JSON file matching ``pattern`` (a glob relative to the
    repository root): its seed, MCP's wait value, the return rates of the players and the paired
    differences with their 95% intervals from its meta."""
    paths = sorted(root.glob(pattern or ""))
    if not paths:
        log.warning(f"demo-seeds: no file matches {pattern!r}")
        return f"*No result file matches `{pattern}`.*"
    head = ["seed", "MCP wait value", *_DEMO_PLAYERS, *(f"{d} [95%]" for d in _DEMO_DIFFERENCES)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for path in paths:
        table = ResultTable.from_json(path)
        rate = {row["player"]: row["rate"] for row in table.rows}
        meta = table.meta
        cells = [str(meta["seed"]), str(meta["wait_value"]),
                 *(f"{rate[name]:.3f}" for name in _DEMO_PLAYERS),
                 *(f"{meta[d]:+.3f} [{meta[d + ' 95% low']:+.3f}, {meta[d + ' 95% high']:+.3f}]"
                   for d in _DEMO_DIFFERENCES)]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    files = ", ".join(f"`{path.relative_to(root)}`" for path in paths)
    return "\n".join([*lines, "", f"*Source: {files}.*"])


_RENDERERS = {
    "gpu-check": lambda root, arg: _gpu_check(root),
    "table": _table,
    "demo-seeds": _demo_seeds,
    "meta-table": _meta_table,
}


def on_page_markdown(markdown: str, page: Any, config: Any, **kwargs: Any) -> str:
    root = Path(config.config_file_path).parent

    def render(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in _RENDERERS:
            log.warning(f"{page.file.src_uri}: unknown results block {name!r}")
            return match.group(0)
        return _RENDERERS[name](root, match.group(2))

    return _MARKER.sub(render, markdown)
