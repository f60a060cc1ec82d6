"""Every reference from the code to a docs page names a page that exists and, with an anchor, a
heading of that page: a docstring that points to ``docs/design/math.md#...`` breaks visibly when
the note is renamed or removed, not silently.

Anchors are the ids the docs site gives its headings: mkdocs' ``toc`` extension with its
default slugify (``markdown.extensions.toc.slugify``: lowercase, characters other than letters,
digits, spaces, hyphens and underscores dropped, spaces turned into hyphens), a repeated heading
getting ``_1``, ``_2``, ... and an explicit ``{#id}`` taking precedence.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from markdown.extensions.toc import slugify, unique

ROOT = Path(__file__).resolve().parents[1]
#: where references are looked for: the package, its tests and benchmarks, the tutorials' sources,
#: and folders of scripts or experiments at the top level where the repository has them
SCANNED = ("hgpdm_torch", "benchmarks", "tests", "notebooks", "experiments", "examples", "scripts")
SUFFIXES = {".py", ".md", ".txt", ".toml", ".cfg", ".yml", ".yaml"}
REFERENCE = re.compile(r"docs/[\w/.-]+\.md(#[\w-]+)?")

_FENCE = re.compile(r"^\s*(```|~~~)")
_HEADING = re.compile(r"^#{1,6}\s+(.*?)(?:\s+#+)?\s*$")
_ATTRS = re.compile(r"\s*\{:?([^}]*)\}\s*$")
_LINK = re.compile(r"!?\[([^\]]*)\]\([^)]*\)")


def heading_anchors(text: str) -> set[str]:
    """The anchor ids of the ATX headings of a Markdown page (outside fenced code blocks)."""
    ids: set[str] = set()
    fenced = False
    for line in text.splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            continue
        match = None if fenced else _HEADING.match(line)
        if match is None:
            continue
        title = match.group(1)
        attrs = _ATTRS.search(title)
        if attrs is not None:
            explicit = re.search(r"#([\w-]+)", attrs.group(1))
            title = title[: attrs.start()]
            if explicit is not None:
                ids.add(explicit.group(1))
                continue
        title = _LINK.sub(r"\1", title).replace("`", "").replace("*", "")
        unique(slugify(title, "-"), ids)
    return ids


def references(text: str) -> list[tuple[str, str | None]]:
    """``(page, anchor or None)`` of every ``docs/<page>.md[#<anchor>]`` reference in ``text``."""
    return [
        (m.group(0).split("#")[0], m.group(1)[1:] if m.group(1) else None)
        for m in REFERENCE.finditer(text)
    ]


def scanned_files() -> list[Path]:
    """The text files under :data:`SCANNED` (those folders that exist)."""
    files = []
    for folder in SCANNED:
        if (ROOT / folder).is_dir():
            files += [
                p
                for p in sorted((ROOT / folder).rglob("*"))
                if p.suffix in SUFFIXES and p.is_file() and "__pycache__" not in p.parts
            ]
    return files


def broken(files: list[Path], root: Path = ROOT) -> list[str]:
    """One line per reference in ``files`` whose page or heading does not exist under ``root``."""
    anchors: dict[Path, set[str]] = {}
    found = []
    for path in files:
        for lineno, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for page, anchor in references(line):
                where = f"{path.relative_to(root)}:{lineno}: {page}"
                target = root / page
                if not target.is_file():
                    found.append(f"{where}: no such page")
                    continue
                if anchor is None:
                    continue
                if target not in anchors:
                    anchors[target] = heading_anchors(target.read_text())
                if anchor not in anchors[target]:
                    found.append(f"{where}#{anchor}: no heading with this anchor")
    return found


REFERENCES = sorted(
    {ref for path in scanned_files() for ref in references(path.read_text(errors="replace"))},
    key=lambda ref: (ref[0], ref[1] or ""),
)


def test_the_code_cites_the_design_pages():
    """The scan finds the citations (so the test below is not vacuous)."""
    pages = {page for page, _ in REFERENCES}
    assert {"docs/design/math.md", "docs/design/speed.md", "docs/design/testing.md"} <= pages
    assert sum(anchor is not None for _, anchor in REFERENCES) >= 10, REFERENCES


def test_every_cited_page_and_heading_exists():
    problems = broken(scanned_files())
    assert problems == [], "references to docs pages that do not exist:\n" + "\n".join(problems)


def test_the_site_slugifies_as_this_test_does():
    """The anchors computed here are the site's only while mkdocs.yml keeps toc's default
    slugify (no ``slugify:`` option) and gives headings their permalinks."""
    config = (ROOT / "mkdocs.yml").read_text()
    assert re.search(r"^\s*- toc:\s*$", config, re.MULTILINE), "mkdocs.yml lost the toc extension"
    assert not re.search(r"^\s*slugify\s*:", config, re.MULTILINE)


@pytest.mark.parametrize(
    ("heading", "anchor"),
    [
        ("## RTS smoothing: the corrected Eq. 26", "rts-smoothing-the-corrected-eq-26"),
        ("### The online filter's Q", "the-online-filters-q"),
        ("## Tolerances on any IEEE-754 machine", "tolerances-on-any-ieee-754-machine"),
        ("## The fused `psi2` contraction", "the-fused-psi2-contraction"),
        ("## See [the guide](../guide.md) ##", "see-the-guide"),
        ("## Custom { #my-id }", "my-id"),
    ],
)  # fmt: skip
def test_heading_anchors_follow_the_toc_slugify(heading, anchor):
    assert heading_anchors(f"# Page\n\n{heading}\n") == {"page", anchor}


def test_repeated_headings_and_code_blocks():
    text = "# A\n\n## Notes\n\n```bash\n# not a heading\n```\n\n## Notes\n"
    assert heading_anchors(text) == {"a", "notes", "notes_1"}


def test_a_broken_anchor_or_page_is_reported(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "page.md").write_text("# Page\n\n## A note\n")
    source = tmp_path / "module.py"
    prefix = "docs/"  # split so that this file's own scan does not see these references
    source.write_text(
        f'"""See {prefix}page.md#a-note, {prefix}page.md#gone and {prefix}missing.md."""\n'
    )
    assert broken([source], tmp_path) == [
        f"module.py:1: {prefix}page.md#gone: no heading with this anchor",
        f"module.py:1: {prefix}missing.md: no such page",
    ]


def test_no_file_cites_the_design_notes_outside_the_repository():
    """The design notes are the docs pages; nothing points to a file outside the repository."""
    outside = re.compile(r"design\.md", re.IGNORECASE)
    pages = sorted((ROOT / "docs").rglob("*.md"))
    hits = [
        f"{path.relative_to(ROOT)}:{n}"
        for path in [*scanned_files(), *pages, ROOT / "README.md", ROOT / "mkdocs.yml"]
        if path.is_file()
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if outside.search(line)
    ]
    assert hits == [], hits
