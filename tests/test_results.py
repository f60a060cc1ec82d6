"""ResultTable's Markdown: one cell per column, whatever the text holds; its JSON, and files
that are not tables named with what is wrong."""

from __future__ import annotations

import re

import pytest

from hgpdm_torch.results import ResultTable


def test_a_pipe_in_a_column_name_or_cell_does_not_split_it():
    table = ResultTable("t", ["name", "|d mean| [cm]"])
    table.add(name="a|b", **{"|d mean| [cm]": 0.5})
    header, rule, row = table.to_markdown().splitlines()[2:]
    for line in (header, rule, row):  # unescaped separators: one more than the columns
        assert line.replace("\\|", "").count("|") == 3
    assert row == "| a\\|b | 0.5 |"


def test_json_round_trip_and_files_that_are_not_tables_named(tmp_path):
    table = ResultTable("t", ["a", "b"], meta={"seed": 1})
    table.add(a=1, b="x")
    table.to_json(tmp_path / "t.json")
    back = ResultTable.from_json(tmp_path / "t.json")
    assert (back.title, back.columns, back.rows, back.meta) == (
        "t",
        ["a", "b"],
        table.rows,
        {"seed": 1},
    )
    text = (tmp_path / "t.json").read_text()
    bad = {
        "cut.json": (text[: len(text) // 2], r"invalid or cut short at line \d+ column \d+ \("),
        "list.json": ("[1, 2]", r"the JSON is a list, not an object"),
        "other.json": ('{"a": 1}', r"no 'title', 'columns', 'rows'\); expected a JSON object"),
        "title.json": ('{"title": 3, "columns": [], "rows": []}', r'"title" is not text'),
        "rows.json": ('{"title": "t", "columns": ["a"], "rows": [1]}', r'"rows" is not a list'),
        "cells.json": ('{"title": "t", "columns": ["a"], "rows": [{"b": 1}]}', r"cells \['b'\]"),
        "meta.json": ('{"title": "t", "columns": [], "rows": [], "meta": 1}', r'"meta" is not'),
    }
    for name, (content, why) in bad.items():
        (tmp_path / name).write_text(content)
        with pytest.raises(ValueError, match=f"{re.escape(str(tmp_path / name))}: .*{why}"):
            ResultTable.from_json(tmp_path / name)
    (tmp_path / "binary.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ValueError, match="binary.json: not a results table \\(not UTF-8"):
        ResultTable.from_json(tmp_path / "binary.json")
