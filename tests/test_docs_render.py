"""The documentation site renders as written: every page of docs/ through Python-Markdown with the extensions of
mkdocs.yml (what `make docs` builds with), and no table cell holds raw Markdown. A heading or a list written right
under a table, with no blank line between, is taken into the table as one more row: the strict build passes, the
page shows "## ..." in a cell, and the heading leaves the table of contents. The home page lists every page."""

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
    names, configs = site_extensions()
    parser = _Cells()
    parser.feed(markdown.markdown(text, extensions=names, extension_configs=configs))
    return [cell.strip() for cell in parser.cells if RAW_MARKDOWN.match(cell.strip())]


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
