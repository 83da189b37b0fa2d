"""The product documentation (README.md, docs/*.md) states what is true now: no history of its making
(issue numbers, sessions, dates, who did what), a short BENCHMARKS.md, relative links that resolve (files and
heading anchors), and every docs page reachable from README.md."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BENCHMARKS = ROOT / "docs" / "BENCHMARKS.md"
BENCHMARKS_MAX_LINES = 500

# Pages whose owners are rewriting them: not yet held to the history rule. Remove a page from this set when
# its rewrite is merged; a new page is checked from the start.
NOT_YET_CHECKED = frozenset()

# Pages the docs may link before they exist (being written); remove a page when it is merged.
PAGES_TO_COME = frozenset()

# History vocabulary: what a page about the product now never needs.
HISTORY = (
    (re.compile(r"\bissues?\s+#?\d+", re.I), "issue number"),
    (re.compile(r"(?<![\w&/(#])#\d+\b"), "'#N' issue reference"),
    (re.compile(r"\bsessions?\s+\d+", re.I), "session number"),
    (re.compile(r"\(lead\)", re.I), "'(lead)'"),
    (re.compile(r"\bquiet re-run\b", re.I), "'quiet re-run'"),
    (re.compile(r"\b(?:19|20)\d\d-[01]\d(?:-[0-3]\d)?\b"), "date"),
    (re.compile(r"\b\d\d:\d\d(?:\s*-\s*\d\d:\d\d)?\s+UTC\b"), "time of day"),
)

LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
FENCE = re.compile(r"^\s*(```|~~~)")


def _pages():
    return [README] + sorted((ROOT / "docs").glob("*.md"))


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _prose_lines(path: Path):
    """(line number, text) of the lines outside fenced code blocks."""
    inside = False
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if FENCE.match(line):
            inside = not inside
            continue
        if not inside:
            yield n, line


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, markup and punctuation dropped, spaces to hyphens."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)          # links: their text
    text = text.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for _, line in _prose_lines(path):
        m = HEADING.match(line)
        if not m:
            continue
        slug = _slug(m.group(2))
        k = seen.get(slug, 0)
        seen[slug] = k + 1
        out.add(slug if k == 0 else f"{slug}-{k}")
    return out


def _links(path: Path):
    """(line number, target) of every relative link of a page (web and mail links skipped)."""
    for n, line in _prose_lines(path):
        for m in LINK.finditer(line):
            target = m.group(1)
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):
                continue
            yield n, target


@pytest.mark.parametrize("page", [p for p in _pages() if _rel(p) not in NOT_YET_CHECKED], ids=_rel)
def test_page_has_no_history_vocabulary(page):
    found = []
    for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        for rx, what in HISTORY:
            for m in rx.finditer(line):
                found.append(f"{_rel(page)}:{n}: {what}: {m.group(0)!r}")
    assert not found, "history of the project's making in the docs (it belongs in git):\n" + "\n".join(found)


def test_benchmarks_is_short():
    n = len(BENCHMARKS.read_text(encoding="utf-8").splitlines())
    assert n <= BENCHMARKS_MAX_LINES, f"docs/BENCHMARKS.md has {n} lines (at most {BENCHMARKS_MAX_LINES}): " \
                                      "keep the current tables only"


@pytest.mark.parametrize("page", _pages(), ids=_rel)
def test_relative_links_resolve(page):
    broken = []
    for n, target in _links(page):
        file_part, _, anchor = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        rel = dest.relative_to(ROOT).as_posix() if dest.is_relative_to(ROOT) else str(dest)
        if not dest.exists():
            if rel in PAGES_TO_COME:
                continue
            broken.append(f"{_rel(page)}:{n}: {target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{_rel(page)}:{n}: {target}: no heading with anchor #{anchor} in {rel}")
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_every_docs_page_is_linked_from_readme():
    linked = {(ROOT / t.partition("#")[0]).resolve() for _, t in _links(README) if t.partition("#")[0]}
    missing = [_rel(p) for p in sorted((ROOT / "docs").glob("*.md")) if p.resolve() not in linked]
    assert not missing, f"docs pages not linked from README.md: {missing}"


def test_the_checker_catches_history_and_resolves_anchors(tmp_path):
    """The rules themselves, on text written for the purpose."""
    bad = ["fixed in issue 7", "see issue #12", "as in #8", "measured in session 5", "re-run (lead)",
           "on 2026-11-22", "at 17:20-17:26 UTC", "the quiet re-run"]
    good = ["section 4.2", "Eq. 3", "[x](BENCHMARKS.md#per-stage-costs)", "1920 x 1080", "`nrhdr env`",
            "colour #ff0000", "50 % missing"]
    for text in bad:
        assert any(rx.search(text) for rx, _ in HISTORY), text
    for text in good:
        assert not any(rx.search(text) for rx, _ in HISTORY), text
    page = tmp_path / "p.md"
    page.write_text("# The 1080p chain and live operation\n## `nrhdr figures`: Figs. 2-10\n## A\n## A\n"
                    "```\n# not a heading\n```\n")
    assert _anchors(page) == {"the-1080p-chain-and-live-operation", "nrhdr-figures-figs-2-10", "a", "a-1"}
