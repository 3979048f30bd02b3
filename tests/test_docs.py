"""README.md, docs/ and notebook/: every relative link points at a file of the repository, and every `#anchor` into a
markdown page at one of its headings (GitHub's slugs)."""

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted([REPO / "README.md", *(REPO / "docs").glob("*.md"), *(REPO / "notebook").glob("*.md")])
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#+\s+(.*)$", text, re.M)}


def links(page: Path) -> list[str]:
    return LINK.findall(FENCE.sub("", page.read_text()))


def test_slug_follows_github():
    assert slug("Choosing an appearance: the SPEC") == "choosing-an-appearance-the-spec"
    assert slug("A camera's path through `get_outputs`") == "a-cameras-path-through-get_outputs"


def test_a_dead_link_is_found(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# Title\n\n[here](missing.md) [there](page.md#title) [nowhere](page.md#nope)\n")
    assert links(page) == ["missing.md", "page.md#title", "page.md#nope"]
    assert not (tmp_path / "missing.md").exists() and "title" in anchors(page) and "nope" not in anchors(page)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(page: Path):
    dead = []
    for target in links(page):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists():
            dead.append(target)
        elif anchor and file.suffix == ".md" and anchor not in anchors(file):
            dead.append(target)
    assert not dead, f"{page.relative_to(REPO)}: dead links {dead}"


def test_the_readmes_demo_time_is_the_measured_one():
    """The README's time for `make demo` is the measurement design.md records (seconds, the install apart), not an
    estimate: the same numbers of seconds in both."""

    def seconds(page: str, anchor: str) -> set[str]:
        text = " ".join((REPO / page).read_text().split())
        start = text.index(anchor)
        return set(re.findall(r"(\d+) s\b", text[start : start + 250]))

    measured = seconds("docs/design.md", "`make demo` (500 steps")
    said = seconds("README.md", "`make install` does.")
    assert said and said <= measured, (said, measured)


def test_the_readme_stays_short():
    """The README is for a user arriving with photos: what to type and where the rest is, in at most 150 lines."""
    assert len((REPO / "README.md").read_text().splitlines()) <= 150
