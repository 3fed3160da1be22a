"""The README and the measurement log under ``docs/``: every relative link reaches its file and anchor.

Anchors are GitHub's: a heading's slug (lower case; letters, digits, ``_``, ``-`` and spaces kept,
spaces turned into ``-``; a repeated slug gets ``-1``, ``-2`` ...) and every ``<a id="...">``.
"""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

from tests._helpers import REPO_ROOT

_LINK = re.compile(r"\]\(([^)\s]+)\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*)$")


def _markdown_files() -> list[Path]:
    return [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").rglob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text."""
    text = re.sub(r"<[^>]+>", "", heading).strip().lower()
    kept = (ch for ch in text if ch in " -" or unicodedata.category(ch)[0] in "LMN" or unicodedata.category(ch) == "Pc")
    return "".join(kept).replace(" ", "-")


def _outside_code(text: str) -> list[str]:
    lines, fenced = [], False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def anchors(text: str) -> set[str]:
    found: set[str] = set()
    seen: dict[str, int] = {}
    for line in _outside_code(text):
        m = _HEADING.match(line)
        if m:
            s = slug(m.group(2))
            n = seen.get(s, 0)
            found.add(s if n == 0 else f"{s}-{n}")
            seen[s] = n + 1
        found.update(re.findall(r'<a id="([^"]+)"', line))
    return found


def broken_links(path: Path) -> list[str]:
    """The relative links of the markdown file ``path`` whose file or anchor does not exist."""
    text = path.read_text()
    broken = []
    for line in _outside_code(text):
        # Inline code may show link syntax without being a link.
        for target in _LINK.findall(re.sub(r"`[^`]*`", "", line)):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
                continue
            file, _, anchor = target.partition("#")
            dest = (path.parent / file).resolve() if file else path
            if not dest.exists():
                broken.append(f"{target} (no file {file})")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text()):
                broken.append(f"{target} (no anchor #{anchor} in {dest.name})")
    return broken


def test_slug_follows_githubs_rule():
    assert slug("NI-SLAM (`python scripts/bench_nislam.py`)") == "ni-slam-python-scriptsbench_nislampy"
    assert slug("Data, evaluation, features") == "data-evaluation-features"
    assert slug("Frames/s × 2 – idle") == "framess--2--idle"
    assert anchors("# A\n## A\n```\n# not a heading\n```\n<a id=\"x\"></a>") == {"a", "a-1", "x"}


def test_the_checker_finds_a_broken_link(tmp_path):
    (tmp_path / "b.md").write_text("# Here\n")
    page = tmp_path / "a.md"
    page.write_text("# Top\n[ok](#top) [ok](b.md#here) [bad](#nowhere) [bad](b.md#there) [bad](c.md) `[code](#x)`\n")
    found = broken_links(page)
    assert len(found) == 3 and [f.split(" ")[0] for f in found] == ["#nowhere", "b.md#there", "c.md"]


@pytest.mark.parametrize("path", _markdown_files(), ids=lambda p: str(p.relative_to(REPO_ROOT)))
def test_every_relative_link_resolves(path):
    assert not broken_links(path), f"{path.relative_to(REPO_ROOT)}: broken links {broken_links(path)}"
