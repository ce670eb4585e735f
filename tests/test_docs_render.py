"""The documentation site renders as written: every page of docs/ through Python-Markdown with the extensions of
mkdocs.yml (what `make docs` builds with), and no table cell holds raw Markdown. A heading or a list written right
under a table, with no blank line between, is taken into the table as one more row: the strict build passes, the
page shows "## ..." in a cell, and the heading leaves the table of contents. Likewise a list right under a line of
a paragraph is more of that paragraph ("Payload: - raw: ... - codebook: ..." on one line), and a heading right under
a line of text is one only by the grace of the renderer (inside a list item it becomes the item's). No table row is
longer than MAX_ROW_CHARS, and no cell shows the backslash of a pipe escaped inside code. The home page lists every
page."""

from __future__ import annotations

import os
import re
from html.parser import HTMLParser

import markdown
import pytest
import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = os.path.join(ROOT, "docs")
PAGES = sorted(os.path.relpath(os.path.join(d, f), ROOT) for d, _, files in os.walk(DOCS) for f in files
               if f.endswith(".md"))
# What Markdown would have made a heading or a list item, left as text in a cell.
RAW_MARKDOWN = re.compile(r"^(#{1,6}\s|[-*+]\s|\d+[.)]\s)")
# A source line that starts a list item or a heading (indented 4 or more, it is a code block or an item's own text).
LIST_ITEM = re.compile(r"^ {0,3}([-*+]|\d+[.)])\s")
HEADING = re.compile(r"^ {0,3}#{1,6}\s")
FENCE = re.compile(r"^\s*(```|~~~)")
# A table row is read across, cell by cell. The site's content column holds about 110 characters of text a line at a
# laptop's width, shared by the row's cells: at 1,000 characters the widest cell already wraps to some 15 lines and the
# row's other cells are out of sight. Prose that long belongs below the table, in a paragraph or a list the row points
# to.
MAX_ROW_CHARS = 1000


def site_config() -> dict:
    with open(os.path.join(ROOT, "mkdocs.yml"), encoding="utf-8") as f:
        return yaml.safe_load(f)


def site_extensions() -> tuple[list[str], dict]:
    """(extension names, their configs) of mkdocs.yml's markdown_extensions."""
    names, configs = [], {}
    for entry in site_config().get("markdown_extensions", []):
        name, options = next(iter(entry.items())) if isinstance(entry, dict) else (entry, None)
        names.append(name)
        if options:
            configs[name] = options
    return names, configs


class _Cells(HTMLParser):
    """The text of every table cell of a page."""

    def __init__(self):
        super().__init__()
        self.cells: list[str] = []
        self._depth = 0

    def handle_starttag(self, tag, attrs):
        if tag in ("td", "th"):
            self._depth += 1
            self.cells.append("")

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._depth:
            self._depth -= 1

    def handle_data(self, data):
        if self._depth:
            self.cells[-1] += data


def raw_markdown_in_cells(text: str) -> list[str]:
    return [cell.strip() for cell in cell_texts(text) if RAW_MARKDOWN.match(cell.strip())]


def cell_texts(text: str) -> list[str]:
    names, configs = site_extensions()
    parser = _Cells()
    parser.feed(markdown.markdown(text, extensions=names, extension_configs=configs))
    return parser.cells


def unbroken_lines(text: str) -> list[str]:
    """'line N: ...' of every list item that follows a paragraph line, and every heading that follows any line,
    with no blank line between (outside fenced code). A list's own lines may follow each other."""
    found, fenced, block = [], False, None  # block: how the current block began (None: after a blank line)
    for n, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced, block = not fenced, "code"
            continue
        if fenced:
            continue
        if not line.strip():
            block = None
        elif HEADING.match(line):
            if block is not None:
                found.append(f"line {n}: {line.strip()[:60]}")
            block = None  # a heading is a block of its own: a list or a paragraph may follow it
        elif LIST_ITEM.match(line):
            if block == "paragraph":
                found.append(f"line {n}: {line.strip()[:60]}")  # the list's first item: the rest follow it
            if block in (None, "paragraph"):
                block = "list"
        elif block is None:
            block = "table" if line.lstrip().startswith("|") else "paragraph"
    return found


def long_rows(text: str) -> list[str]:
    return [f"line {n}: {len(line)} characters" for n, line in enumerate(text.splitlines(), 1)
            if line.lstrip().startswith("|") and len(line) > MAX_ROW_CHARS]


def visible_backslashes(text: str) -> list[str]:
    """Cells that show a backslash before a pipe: inside a code span Markdown keeps the `\\|` GitHub would hide."""
    return [cell.strip() for cell in cell_texts(text) if "\\|" in cell]


def _page(page: str) -> str:
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        return f.read()


@pytest.mark.parametrize("page", PAGES)
def test_lists_and_headings_start_after_a_blank_line(page):
    found = unbroken_lines(_page(page))
    assert not found, (f"{page}: a list or heading right under a line of text renders as part of it; put a blank line "
                       f"before it: {found}")


@pytest.mark.parametrize("page", PAGES)
def test_no_table_row_is_prose(page):
    found = long_rows(_page(page))
    assert not found, (f"{page}: table rows over {MAX_ROW_CHARS} characters; keep the cell short and move the rest "
                       f"below the table: {found}")


@pytest.mark.parametrize("page", PAGES)
def test_no_cell_shows_an_escaped_pipe(page):
    found = visible_backslashes(_page(page))
    assert not found, f"{page}: cells show a backslash (a pipe escaped inside code); write the values apart: {found}"


def test_the_checks_see_what_they_look_for():
    assert unbroken_lines("Payload:\n- raw\n- codebook\n\ntext\n## Next\n") == ["line 2: - raw", "line 6: ## Next"]
    assert unbroken_lines("Payload:\n\n- raw\n  more\n- codebook\n\n## Next\ntext\n1. one\n") == ["line 9: 1. one"]
    assert unbroken_lines("```\ntext\n- not a list\n# nor a heading\n```\n") == []
    assert long_rows("| a |\n| " + "x" * MAX_ROW_CHARS + " |\n") == ["line 2: 1004 characters"]
    assert long_rows("| a |\n| " + "x" * (MAX_ROW_CHARS - 4) + " |\n") == []
    table = "| a | b |\n| --- | --- |\n| `N=1\\|3` | y |\n"
    assert visible_backslashes(table) == ["N=1\\|3"]
    assert visible_backslashes(table.replace("`N=1\\|3`", "N=1\\|3")) == []  # outside code the escape hides


@pytest.mark.parametrize("page", PAGES)
def test_no_table_cell_shows_raw_markdown(page):
    with open(os.path.join(ROOT, page), encoding="utf-8") as f:
        found = raw_markdown_in_cells(f.read())
    assert not found, (f"{page}: table cells show raw Markdown (a heading or list right under a table needs a blank "
                       f"line before it): {found}")


def test_the_check_sees_a_heading_swallowed_by_a_table():
    swallowed = "| a | b |\n| --- | --- |\n| 1 | 2 |\n## Next\n- item\n"
    assert raw_markdown_in_cells(swallowed) == ["## Next", "- item"]
    assert raw_markdown_in_cells(swallowed.replace("| 1 | 2 |\n", "| 1 | 2 |\n\n")) == []


def _nav_pages(entry) -> list[str]:
    if isinstance(entry, str):
        return [entry]
    items = entry.values() if isinstance(entry, dict) else entry
    return [page for item in items for page in _nav_pages(item)]


def test_the_home_page_lists_every_page():
    with open(os.path.join(DOCS, "index.md"), encoding="utf-8") as f:
        links = set(re.findall(r"\]\(([^)#\s]+)", f.read()))
    missing = [page for page in _nav_pages(site_config()["nav"]) if page != "index.md" and page not in links]
    assert not missing, f"docs/index.md links no {missing} (every page of mkdocs.yml's nav belongs on the home page)"
