"""The user's documentation: links that resolve, a README that stays short, pointers that name real sections.

``make docs`` builds the site with ``mkdocs build --strict`` (CI runs it), which checks the links between the
pages of ``docs/`` as the site shows them. These tests check the same Markdown as GitHub shows it — README.md,
CHANGELOG.md and every page of docs/ — without MkDocs: each relative link names a file that exists, and each
``#anchor`` a heading of the Markdown file it points to (GitHub's slugs), so a renamed section or a moved
page fails here before a reader finds the dead link.
"""

import re
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r'!?\[[^\]\n]*\]\(([^)\s]+)(?:\s+"[^"\n]*")?\)')
FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.MULTILINE)
EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: markup dropped, lower case, punctuation removed, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)          # a link keeps its text
    text = re.sub(r"[`*_]", lambda m: "_" if m.group(0) == "_" else "", text).strip().lower()
    text = "".join(ch for ch in text if ch in " -_" or unicodedata.category(ch)[0] in "LN")
    return text.replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    """Every anchor a Markdown file has: its headings' slugs, numbered -1, -2, … when repeated."""
    seen: dict[str, int] = {}
    out = set()
    for heading in HEADING.findall(FENCE.sub("", markdown)):
        base = slug(heading)
        count = seen.get(base, 0)
        seen[base] = count + 1
        out.add(base if count == 0 else f"{base}-{count}")
    return out


def broken_links(page: Path, root: Path = REPO) -> list[str]:
    """The relative links of one Markdown file that point to no file, or to no heading of the file they name."""
    text = FENCE.sub("", page.read_text(encoding="utf-8"))
    problems = []
    for target in LINK.findall(text):
        if EXTERNAL.match(target) or target.startswith("/"):
            continue
        path, _, anchor = target.partition("#")
        file = (page.parent / path).resolve() if path else page
        if not file.exists() or root not in (file, *file.parents):
            problems.append(f"{page.relative_to(root)}: {target}: no such file")
        elif anchor and file.suffix == ".md" and anchor not in anchors(file.read_text(encoding="utf-8")):
            problems.append(f"{page.relative_to(root)}: {target}: no heading '#{anchor}' in {file.name}")
    return problems


def markdown_files() -> list[Path]:
    return [REPO / "README.md", REPO / "CHANGELOG.md", *sorted((REPO / "docs").rglob("*.md"))]


@pytest.mark.parametrize("page", markdown_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(page):
    assert broken_links(page) == []


def test_the_link_check_finds_a_missing_page_and_a_missing_anchor(tmp_path):
    (tmp_path / "guide.md").write_text("# Guide\n\n## The command line\n\ntext\n")
    page = tmp_path / "index.md"
    page.write_text("[ok](guide.md#the-command-line) [gone](missing.md) [no anchor](guide.md#outputs)\n"
                    "```sh\n[in a code block](ignored.md)\n```\n")
    assert broken_links(page, tmp_path) == ["index.md: missing.md: no such file",
                                            "index.md: guide.md#outputs: no heading '#outputs' in guide.md"]


def test_slugs_follow_github():
    assert slug("Outputs (`tofcore.write_frame`)") == "outputs-tofcorewrite_frame"
    assert slug("7. Depth noise against distance: the presets") == "7-depth-noise-against-distance-the-presets"
    assert slug("Tested in a real Blender GUI: `make test-blender`") == "tested-in-a-real-blender-gui-make-test-blender"
    assert anchors("# A\n## B\n## B\n```\n# not a heading\n```\n") == {"a", "b", "b-1"}


def test_the_readme_is_an_introduction_not_a_notebook():
    """About 250 lines (it was 954, with dated measurements and run-by-run test stories): the details live in
    docs/, the history in CHANGELOG.md."""
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 300
    for section in ("## Install", "## Quickstart", "## Three ways to use it", "## Documentation"):
        assert section in readme


def test_every_docs_page_is_in_the_site_navigation():
    """mkdocs --strict reports pages left out of the nav too; this says which one without building."""
    config = (REPO / "mkdocs.yml").read_text(encoding="utf-8")
    listed = set(re.findall(r":\s*(\S+\.md)\s*$", config, re.MULTILINE))
    pages = {str(p.relative_to(REPO / "docs")) for p in (REPO / "docs").rglob("*.md")}
    assert pages == listed


def test_the_add_on_points_to_sections_that_exist():
    """The add-on's "install by hand (FILE, SECTION)" messages name a heading of that file."""
    source = (REPO / "addon" / "preferences.py").read_text(encoding="utf-8")
    pointers = re.findall(r'"(docs/[\w.]+\.md), ([^"]+)"', source)
    assert len(pointers) == 2
    for file, section in pointers:
        assert slug(section) in anchors((REPO / file).read_text(encoding="utf-8")), (file, section)
