"""A small result table that every experiment returns: printable as Markdown, savable as JSON."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["ResultTable"]


@dataclass
class ResultTable:
    """Rows of named values, in the layout of a thesis table.

    Attributes:
        title: what the table shows (e.g. "Table 3.2: target prediction MAE [m]").
        columns: column names, in order.
        rows: one dict per row, keyed by column name.
        meta: free-form settings needed to reproduce the table (seed, sizes, command).
    """

    title: str
    columns: list[str]
    rows: list[dict[str, Any]] = field(default_factory=list)
    meta: dict[str, Any] = field(default_factory=dict)

    def add(self, **values: Any) -> None:
        """Append a row; every key must be a known column."""
        unknown = set(values) - set(self.columns)
        if unknown:
            raise ValueError(f"unknown columns {sorted(unknown)}; table has {self.columns}")
        self.rows.append(values)

    def column(self, name: str) -> list[Any]:
        """All values of one column (missing cells are None)."""
        if name not in self.columns:
            raise ValueError(f"unknown column {name!r}; table has {self.columns}")
        return [row.get(name) for row in self.rows]

    def to_markdown(self, floatfmt: str = ".4g") -> str:
        """The table as GitHub Markdown, with the title as a bold caption."""

        def fmt(v: Any) -> str:
            if v is None:
                return ""
            if isinstance(v, float):
                return format(v, floatfmt)
            return str(v).replace("|", "\\|")  # a bare | would split the cell

        lines = [f"**{self.title}**", "", "| " + " | ".join(map(fmt, self.columns)) + " |"]
        lines.append("|" + "|".join("---" for _ in self.columns) + "|")
        for row in self.rows:
            lines.append("| " + " | ".join(fmt(row.get(c)) for c in self.columns) + " |")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.to_markdown()

    def to_json(self, path: str | Path) -> None:
        """Write title, columns, rows and meta as JSON."""
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "title": self.title,
            "columns": self.columns,
            "rows": self.rows,
            "meta": self.meta,
        }
        Path(path).write_text(json.dumps(payload, indent=2, default=float))

    @classmethod
    def from_json(cls, path: str | Path) -> ResultTable:
        """Read a table written by :meth:`to_json`.

        Raises:
            ValueError: the file is not UTF-8 JSON text (the message names the file and, for bad
                JSON, the line and column), or its JSON is not a table: an object with
                ``"title"`` (text), ``"columns"`` (a list of names), ``"rows"`` (a list of
                objects keyed by those names) and optionally ``"meta"`` (an object).
            OSError: the file cannot be read.
        """
        try:
            d = json.loads(Path(path).read_text(encoding="utf-8"))
        except UnicodeDecodeError:
            raise ValueError(f"{path}: not a results table (not UTF-8 JSON text)") from None
        except json.JSONDecodeError as err:
            raise ValueError(
                f"{path}: not a results table, its JSON is invalid or cut short at line "
                f"{err.lineno} column {err.colno} ({err.msg})"
            ) from None
        problem = _table_problem(d)
        if problem:
            raise ValueError(
                f"{path}: not a results table ({problem}); expected a JSON object with "
                '"title" (text), "columns" (a list of names), "rows" (a list of objects keyed by '
                'those names) and optionally "meta" (an object), as ResultTable.to_json writes'
            )
        return cls(d["title"], d["columns"], d["rows"], d.get("meta", {}))


def _table_problem(d: Any) -> str:
    """What keeps the parsed JSON ``d`` from being a :class:`ResultTable` ("" if nothing)."""
    if not isinstance(d, dict):
        return f"the JSON is a {type(d).__name__}, not an object"
    missing = [key for key in ("title", "columns", "rows") if key not in d]
    if missing:
        return f"no {', '.join(map(repr, missing))}"
    columns, rows = d["columns"], d["rows"]
    if not isinstance(d["title"], str):
        return '"title" is not text'
    if not isinstance(columns, list) or not all(isinstance(c, str) for c in columns):
        return '"columns" is not a list of names'
    if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
        return '"rows" is not a list of objects'
    unknown = sorted({k for r in rows for k in r} - set(columns))
    if unknown:
        return f"rows have cells {unknown} outside the columns"
    if not isinstance(d.get("meta", {}), dict):
        return '"meta" is not an object'
    return ""
