"""ResultTable's Markdown: one cell per column, whatever the text holds."""

from __future__ import annotations

from hgpdm_torch.results import ResultTable


def test_a_pipe_in_a_column_name_or_cell_does_not_split_it():
    table = ResultTable("t", ["name", "|d mean| [cm]"])
    table.add(name="a|b", **{"|d mean| [cm]": 0.5})
    header, rule, row = table.to_markdown().splitlines()[2:]
    for line in (header, rule, row):  # unescaped separators: one more than the columns
        assert line.replace("\\|", "").count("|") == 3
    assert row == "| a\\|b | 0.5 |"
