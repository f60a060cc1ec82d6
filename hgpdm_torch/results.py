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
        """Read a table written by :meth:`to_json`."""
        d = json.loads(Path(path).read_text())
        return cls(d["title"], d["columns"], d["rows"], d.get("meta", {}))
