"""Every relative link in README.md, docs/*.md and deploy/README.md leads somewhere: the file or folder
exists, and a #anchor names a heading of the Markdown file it points into (GitHub's heading ids).
The links are read by a Markdown parser (markdown-it-py, which rich brings), so a link shown inside
code is not taken for one."""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import unquote

import pytest
from markdown_it import MarkdownIt

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "deploy" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
MD = MarkdownIt("commonmark")


def heading_ids(text: str) -> set[str]:
    """The ids GitHub gives a page's headings: the heading's text lower-cased, punctuation but
    hyphens and underscores dropped, spaces made hyphens; a repeated id gets -1, -2, ..."""
    ids: set[str] = set()
    tokens = MD.parse(text)
    for k, tok in enumerate(tokens):
        if tok.type != "heading_open":
            continue
        inline = tokens[k + 1]
        plain = "".join(child.content for child in inline.children or [] if child.type in ("text", "code_inline"))
        slug = re.sub(r"[^\w\- ]", "", plain.strip().lower()).replace(" ", "-")
        unique, n = slug, 0
        while unique in ids:
            n += 1
            unique = f"{slug}-{n}"
        ids.add(unique)
    return ids


def links(text: str) -> list[str]:
    out = []
    for tok in MD.parse(text):
        for child in tok.children or []:
            if child.type == "link_open":
                out.append(child.attrs["href"])
    return out


def broken_links(page: Path) -> list[str]:
    problems = []
    for href in links(page.read_text(encoding="utf-8")):
        if re.match(r"[a-z][a-z0-9+.-]*:", href):  # http:, https:, mailto:: not ours to check
            continue
        target, _, anchor = href.partition("#")
        path = page if not target else (page.parent / unquote(target)).resolve()
        if not path.exists():
            problems.append(f"{href}: no such file")
        elif anchor and path.suffix == ".md" and unquote(anchor) not in heading_ids(path.read_text(encoding="utf-8")):
            problems.append(f"{href}: no heading #{anchor} in {target or page.name}")
    return problems


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_relative_link_resolves(page):
    assert broken_links(page) == []


def test_the_checker_finds_a_missing_file_and_a_missing_heading(tmp_path):
    (tmp_path / "other.md").write_text("# Other page\n\n## `--drones N`: sizing the formation\n\n## Twice\n\n## Twice\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#--drones-n-sizing-the-formation) [ok](other.md#twice-1) [ok](#a-heading)\n\n"
                    "# A heading\n\n[gone](nowhere.md) [no anchor](other.md#no-such-heading) `[code](nowhere.md)`\n")
    assert broken_links(page) == ["nowhere.md: no such file",
                                  "other.md#no-such-heading: no heading #no-such-heading in other.md"]
