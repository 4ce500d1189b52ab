"""Every relative link in README.md and docs/*.md points to a file that exists (and to a heading that exists).

Links are read as Markdown renders them: fenced code blocks and inline code are skipped, external links
(``http:``, ``https:``, ``mailto:``) are not checked. ``#anchor`` parts are checked against the target's
headings with GitHub's rule for heading ids.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.S | re.M)
INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+?\1", re.S)
EXTERNAL = ("http://", "https://", "mailto:")


def links(text: str) -> list[str]:
    text = FENCE.sub("", text)
    text = INLINE_CODE.sub("", text)
    return LINK.findall(text)


def heading_ids(text: str) -> set[str]:
    """GitHub's ids: lower case, markup and punctuation dropped (hyphens and underscores kept), spaces to hyphens;
    a repeated heading gets -1, -2, ..."""
    ids: set[str] = set()
    for line in FENCE.sub("", text).splitlines():
        m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        title = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", m.group(1))  # a link in a heading keeps its text
        slug = re.sub(r"[^\w\- ]", "", title.replace("`", "").lower()).replace(" ", "-")
        candidate, n = slug, 0
        while candidate in ids:
            n += 1
            candidate = f"{slug}-{n}"
        ids.add(candidate)
    return ids


def check_page(page: Path, root: Path = REPO) -> list[str]:
    problems = []
    for target in links(page.read_text(encoding="utf-8")):
        if target.startswith(EXTERNAL):
            continue
        path_part, _, anchor = target.partition("#")
        file = (page.parent / path_part).resolve() if path_part else page
        rel = file.relative_to(root).as_posix() if file.is_relative_to(root) else str(file)
        if not file.exists():
            problems.append(f"{page.relative_to(root)}: link {target!r}: {rel} does not exist")
        elif anchor and file.suffix == ".md" and anchor not in heading_ids(file.read_text(encoding="utf-8")):
            problems.append(f"{page.relative_to(root)}: link {target!r}: no heading #{anchor} in {rel}")
    return problems


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_point_to_existing_files(page):
    assert check_page(page) == []


def test_the_checker_sees_what_it_should(tmp_path):
    """The parts of the rule, on a page made up for the purpose."""
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs/a.md").write_text("# A page\n\n## The `main` job: run it\n")
    page = tmp_path / "README.md"
    page.write_text(
        "[ok](docs/a.md) [ok anchor](docs/a.md#the-main-job-run-it) [self](#top) ![img](docs/missing.png)\n"
        "[bad anchor](docs/a.md#nope) [web](https://example.com/x.md) `[in code](docs/nothing.md)`\n"
        "[gone](docs/results.md)\n\n# Top\n\n```\n[in a block](docs/nothing.md)\n```\n"
    )
    assert check_page(page, root=tmp_path) == [
        "README.md: link 'docs/missing.png': docs/missing.png does not exist",
        "README.md: link 'docs/a.md#nope': no heading #nope in docs/a.md",
        "README.md: link 'docs/results.md': docs/results.md does not exist",
    ]
