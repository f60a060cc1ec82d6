"""Every tutorial notebook and its paired percent-format source (notebooks/NAME.py, see
notebooks/jupytext.toml) hold the same cells: edit one, then `jupytext --sync notebooks/*.ipynb`
(or `make notebooks`)."""

from __future__ import annotations

from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
IPYNB = sorted(NOTEBOOKS.glob("*.ipynb"))
SOURCES = sorted(NOTEBOOKS.glob("*.py"))


def cells(path: Path) -> list[tuple[str, str]]:
    nb = jupytext.read(path)
    return [(cell.cell_type, cell.source.rstrip("\n")) for cell in nb.cells]


def test_every_notebook_has_its_source():
    assert IPYNB, "no notebooks found"
    assert [p.stem for p in IPYNB] == [p.stem for p in SOURCES]


@pytest.mark.parametrize("notebook", IPYNB, ids=lambda p: p.stem)
def test_notebook_matches_its_source(notebook: Path):
    source = notebook.with_suffix(".py")
    assert source.is_file(), f"{source.name} is missing: run jupytext --sync {notebook.name}"
    in_notebook, in_source = cells(notebook), cells(source)
    for k, (a, b) in enumerate(zip(in_notebook, in_source, strict=False)):
        assert a == b, (
            f"cell {k} differs between {notebook.name} and {source.name}; run "
            f"`jupytext --sync notebooks/{notebook.name}` after editing one of them"
        )
    assert len(in_notebook) == len(in_source), (
        f"{notebook.name} has {len(in_notebook)} cells, {source.name} {len(in_source)}"
    )
