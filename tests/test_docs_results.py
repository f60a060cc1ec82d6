"""Every result table a docs page cites is a committed JSON file that reads as a ResultTable, and
the README stays a front page (the results live on the docs site)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from hgpdm_torch.results import ResultTable

ROOT = Path(__file__).resolve().parents[1]
MARKER = re.compile(r"^<!-- results: table ([\w./-]+) -->$", re.MULTILINE)
CITED = sorted(
    (page.relative_to(ROOT), name)
    for page in (ROOT / "docs").rglob("*.md")
    for name in MARKER.findall(page.read_text())
)


def test_the_docs_cite_result_tables():
    assert len(CITED) >= 4, CITED


META = re.compile(r"^<!-- results: meta-table ([\w./-]+)#(\w+) -->$", re.MULTILINE)
META_TABLES = sorted(
    (page.relative_to(ROOT), name, key)
    for page in (ROOT / "docs").rglob("*.md")
    for name, key in META.findall(page.read_text())
)


@pytest.mark.parametrize(
    ("page", "name", "key"), META_TABLES, ids=[f"{p}:{n}#{k}" for p, n, k in META_TABLES]
)
def test_cited_meta_records_exist(page, name, key):
    path = ROOT / name
    assert path.is_file(), f"{page} cites {name}, which does not exist"
    records = ResultTable.from_json(path).meta.get(key)
    assert isinstance(records, list) and records and all(isinstance(r, dict) for r in records), (
        f"{page} cites the records {key!r} of {name}, which its meta does not hold"
    )


GLOBS = re.compile(r"^<!-- results: demo-seeds ([\w./*-]+) -->$", re.MULTILINE)
SEED_TABLES = sorted(
    (page.relative_to(ROOT), pattern)
    for page in (ROOT / "docs").rglob("*.md")
    for pattern in GLOBS.findall(page.read_text())
)


@pytest.mark.parametrize(("page", "pattern"), SEED_TABLES, ids=[f"{p}:{n}" for p, n in SEED_TABLES])
def test_cited_demo_runs_exist_and_hold_what_the_summary_reads(page, pattern):
    paths = sorted(ROOT.glob(pattern))
    assert paths, f"{page} cites {pattern}, which matches no file"
    for path in paths:
        table = ResultTable.from_json(path)
        players = {row["player"] for row in table.rows}
        assert {"LSPI", "MCP", "best fixed time (training folds)"} <= players, path
        assert {"seed", "wait_value", "MCP - best fixed time (training folds) 95% low"} <= set(
            table.meta
        ), path


@pytest.mark.parametrize(("page", "name"), CITED, ids=[f"{p}:{n}" for p, n in CITED])
def test_cited_result_table_exists_and_reads(page, name):
    path = ROOT / name
    assert path.is_file(), f"{page} cites {name}, which does not exist"
    table = ResultTable.from_json(path)
    assert table.rows and table.columns, f"{name} holds no table"


README_MAX_LINES = 250


def test_readme_is_a_front_page():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, (
        f"README.md has {len(lines)} lines (at most {README_MAX_LINES}): move results and "
        "reference prose to a page under docs/"
    )
