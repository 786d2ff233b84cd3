"""Every relative link of the committed Markdown pages points at a file of the repository, and every
`page.md#section` link at a heading of that page, as GitHub names headings' anchors. A page's heading
renamed (a campaign's "(in progress)" dropped) breaks the links to it; this test names them. A link to a
line of code, [`name`, file.py:N](file.py#LN), must still land on the line that defines or assigns `name`: code moved
above it shifts the line."""

from __future__ import annotations

import os
import re
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LINK = re.compile(r"\]\(([^)\s]+)\)")
HEADING = re.compile(r"^#{1,6} +(.+?) *#* *$")
CODE_LINE_LINK = re.compile(r"\[`([^`]+)`, ([^\]:]+):(\d+)\]\(([^)#\s]+)#L(\d+)\)")


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: its text without markup, lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    """The anchors of a page's headings (outside code blocks), a repeated one numbered as GitHub does."""
    found, fenced = [], False
    for line in markdown.splitlines():
        fenced ^= line.startswith("```")
        heading = HEADING.match(line)
        if heading and not fenced:
            name = anchor(heading.group(1))
            found.append(name if name not in found else f"{name}-{found.count(name)}")
    return set(found)


def broken_links(page: str, markdown: str) -> list[str]:
    """The relative links of a page (at `page`, relative to the root) to no file, or to no heading of a page."""
    broken = []
    for target in LINK.findall(markdown):
        if re.match(r"[a-z]+:", target):
            continue
        path, _, section = target.partition("#")
        linked = os.path.normpath(os.path.join(os.path.dirname(page), path)) if path else page
        if not os.path.exists(os.path.join(ROOT, linked)):
            broken.append(f"{page}: ({target}) names no file")
        elif section and linked.endswith(".md"):
            with open(os.path.join(ROOT, linked)) as f:
                if section not in anchors(f.read()):
                    broken.append(f"{page}: ({target}) names no heading of {linked}")
    return broken


def test_a_heading_anchor_is_githubs():
    assert anchor("Past the collapse point: 3M and 5.5M steps (in progress)") == \
        "past-the-collapse-point-3m-and-55m-steps-in-progress"
    assert anchor("Level scores (`--score-function`)") == "level-scores---score-function"
    assert anchor("The [maze](docs/envs.md) and **its** mazes") == "the-maze-and-its-mazes"
    assert anchors("# Notes\n```\n# a comment\n```\n## Notes\n") == {"notes", "notes-1"}


def test_every_relative_link_of_the_pages_points_at_a_file_and_a_heading():
    pages = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    assert "README.md" in pages and "results/README.md" in pages
    broken, links = [], 0
    for page in pages:
        with open(os.path.join(ROOT, page)) as f:
            markdown = f.read()
        links += len(LINK.findall(markdown))
        broken += broken_links(page, markdown)
    assert links >= 50
    assert not broken, "; ".join(broken)
    renamed = "# cleanued\n[the page](results/README.md#past-the-collapse-point-3m-and-55m-steps)\n"
    assert broken_links("README.md", renamed) == [
        "README.md: (results/README.md#past-the-collapse-point-3m-and-55m-steps) names no heading of results/README.md"]


def stale_code_line_links(page: str, markdown: str) -> list[str]:
    """The links of a page to a line of code whose text and anchor disagree, or whose line no longer holds the
    name it is given."""
    stale = []
    for name, shown_path, shown_line, path, line in CODE_LINE_LINK.findall(markdown):
        linked = os.path.normpath(os.path.join(os.path.dirname(page), path))
        if linked != os.path.normpath(shown_path) or shown_line != line:
            stale.append(f"{page}: [{name}, {shown_path}:{shown_line}] links to {linked}#L{line}")
            continue
        with open(os.path.join(ROOT, linked)) as f:
            lines = f.read().splitlines()
        defines = re.compile(rf"\s*(def |class )?{re.escape(name)}\s*[(:=]")  # def, class, field or assignment
        if not (0 < int(line) <= len(lines) and defines.match(lines[int(line) - 1])):
            holding = [i + 1 for i, text in enumerate(lines) if defines.match(text)]
            stale.append(f"{page}: {linked}:{line} does not define {name} (lines that do: {holding[:3]})")
    return stale


def test_every_link_to_a_line_of_code_lands_on_its_name():
    pages = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    stale, links = [], 0
    for page in pages:
        with open(os.path.join(ROOT, page)) as f:
            markdown = f.read()
        links += len(CODE_LINE_LINK.findall(markdown))
        stale += stale_code_line_links(page, markdown)
    assert links >= 20
    assert not stale, "; ".join(stale)
    moved = "[`resolve_args`, plr.py:1](plr.py#L1)\n[`Args`, plr.py:2](plr.py#L3)\n"
    assert len(stale_code_line_links("README.md", moved)) == 2
