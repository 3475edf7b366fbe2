"""The documentation stands alone: no pointers outside the repository, no broken relative links.

A user's clone has only the repository, so README.md and docs/ must not send readers to the
maintainers' sibling folders, and every relative Markdown link must lead to a file that exists
(and, with an #anchor into a Markdown file, to a heading that exists); so must a docs page and
heading named in code or configuration (pyproject.toml's docs/design.md#layout).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()

# Spelled in pieces so that this file does not match itself.
OUTSIDE_POINTERS = ("../" + "shared", "shared" + "/docs")

INLINE_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_DEF = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+\"[^\"]*\")?\s*$", re.MULTILINE)
FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1", re.DOTALL)
HEADING = re.compile(r"^#{1,6}\s+(.+?)\s*#*\s*$", re.MULTILINE)
# A page and heading named in code or configuration, e.g. pyproject.toml's "docs/design.md#layout".
DOC_ANCHOR = re.compile(r"\b((?:docs|deploy)/[\w./-]+\.md)#([\w-]+)")


def _markdown_files() -> list[Path]:
    """README.md, the changelog, the deploy and shipped-data notes, and every Markdown file under docs/."""
    notes = [REPO / "CHANGELOG.md", REPO / "deploy" / "README.md", REPO / "aefabmap" / "data" / "README.md"]
    return [REPO / "README.md", *notes, *sorted((REPO / "docs").rglob("*.md"))]


def _files_for_pointer_check() -> list[Path]:
    """README, everything under docs/, and the project's own notes, scripts and code."""
    files = [REPO / "README.md", REPO / "pyproject.toml"]
    files += [p for p in sorted((REPO / "docs").rglob("*")) if p.is_file()]
    for folder in ("deploy", "scripts", "runtime", "trainer", "export", "aefabmap", "tests"):
        for p in sorted((REPO / folder).rglob("*")):
            if p.is_file() and p.suffix in {".md", ".py", ".sh", ".toml", ".txt", ".service", ".json5"}:
                files.append(p)
    return [p for p in files if p.resolve() != THIS and "__pycache__" not in p.parts]


def outside_pointers(text: str) -> list[str]:
    """Lines of text that point at the maintainers' sibling folders."""
    return [line.strip() for line in text.splitlines() if any(p in line for p in OUTSIDE_POINTERS)]


def _prose(text: str) -> str:
    """Markdown without fenced code blocks and inline code spans.

    Indented lines are kept: they are as often nested list items as code, and the project's
    indented code blocks (shell commands) hold no `](`.
    """
    return CODE_SPAN.sub("", FENCE.sub("", text))


def relative_links(text: str) -> list[str]:
    """Targets of inline and reference-style links that are neither URLs nor in-page anchors."""
    prose = _prose(text)
    targets = INLINE_LINK.findall(prose) + REFERENCE_DEF.findall(prose)
    return [t for t in targets if not re.match(r"^([a-z][a-z0-9+.-]*:|#)", t, re.IGNORECASE)]


def heading_anchors(text: str) -> set[str]:
    """GitHub-style anchors of a Markdown file's headings."""
    anchors = set()
    for title in HEADING.findall(FENCE.sub("", text)):
        title = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", title).replace("`", "").lower()
        anchors.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return anchors


def broken_links(md: Path, root: Path = REPO) -> list[str]:
    """Relative links of one Markdown file whose file (or heading anchor) does not exist."""
    bad = []
    name = md.relative_to(root)
    for target in relative_links(md.read_text(encoding="utf-8")):
        path, _, anchor = target.partition("#")
        dest = (md.parent / path).resolve()
        if not dest.exists():
            bad.append(f"{name}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor.lower() not in heading_anchors(dest.read_text(encoding="utf-8")):
            bad.append(f"{name}: {target} (no such heading)")
    return bad


def test_docs_name_no_folder_outside_the_repository():
    bad = []
    for f in _files_for_pointer_check():
        try:
            text = f.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        bad += [f"{f.relative_to(REPO)}: {line}" for line in outside_pointers(text)]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("md", _markdown_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_lead_to_existing_files(md):
    assert md.is_file()
    assert not (bad := broken_links(md)), "\n".join(bad)


def test_pages_and_headings_named_outside_markdown_exist():
    """Code and configuration that send a reader to docs/PAGE.md#heading name one that exists."""
    bad = []
    for f in _files_for_pointer_check():
        if f.suffix == ".md":
            continue  # Markdown links are checked above
        try:
            text = f.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue
        for page, anchor in DOC_ANCHOR.findall(text):
            dest = REPO / page
            if not dest.is_file():
                bad.append(f"{f.relative_to(REPO)}: {page}#{anchor} (no such file)")
            elif anchor.lower() not in heading_anchors(dest.read_text(encoding="utf-8")):
                bad.append(f"{f.relative_to(REPO)}: {page}#{anchor} (no such heading)")
    assert not bad, "\n".join(bad)


def test_the_model_protocol_and_data_are_documented():
    for name in ("fabmap2.md", "evaluation.md", "data.md"):
        assert (REPO / "docs" / name).is_file(), f"docs/{name} is missing"
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    for name in ("docs/fabmap2.md", "docs/evaluation.md", "docs/data.md"):
        assert f"]({name}" in readme, f"README.md does not link {name}"


def test_checkers_see_violations(tmp_path):
    """The checks themselves work: a pointer outside the repo and dead links are caught."""
    assert outside_pointers("see " + OUTSIDE_POINTERS[0] + "/docs/x.md\nfine line")
    assert outside_pointers("in " + OUTSIDE_POINTERS[1] + "/fabmap2.md")
    assert not outside_pointers("default: a shared/data folder beside the checkout")
    (tmp_path / "there.md").write_text("# A heading\n", encoding="utf-8")
    md = tmp_path / "page.md"
    md.write_text(
        "[ok](there.md) [ok](there.md#a-heading) [web](https://example.org/x.md) [top](#here)\n"
        "[gone](missing.md) [bad anchor](there.md#nope)\n"
        "`[code](not-a-link.md)`\n\n```\n[fenced](not-a-link.md)\n```\n  * nested [ok](there.md)\n",
        encoding="utf-8",
    )
    assert relative_links(md.read_text()) == ["there.md", "there.md#a-heading", "missing.md", "there.md#nope", "there.md"]
    assert broken_links(md, tmp_path) == ["page.md: missing.md (no such file)", "page.md: there.md#nope (no such heading)"]
