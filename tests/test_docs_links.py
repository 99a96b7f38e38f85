"""Every link and file path named in README.md, docs/*.md and docs/notebook/*.md resolves to a file of the repository.

Issue 21, item 5: the front door and the docs cite the repository's own files (docs/spec.md is the
spec), never a path outside it such as ``../shared/SPEC.md``. Checked: markdown links and images
(relative to the page, as a renderer resolves them) and file paths written in backticks (relative to
the repository root, as the docs write them, or a bare ``name.md`` beside the page; paths a run creates, under ``runs/`` or ``data/``, and
patterns with ``*`` or ``<...>`` are not files to check).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs" / "notebook").glob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
CODE = re.compile(r"`([^`\s]+)`")
FILE_EXT = (".md", ".py", ".yaml", ".yml", ".toml", ".sh", ".png", ".tex", ".ckpt", ".json", ".txt")
MADE_BY_RUNS = ("runs/", "data/", ".venv/", "$")


def _outside(path: Path) -> bool:
    try:
        path.resolve().relative_to(ROOT)
        return False
    except ValueError:
        return True


def references(page: Path) -> list[tuple[int, str, Path]]:
    """``(line, reference, resolved path)`` of every file reference on ``page`` that must exist."""
    out = []
    for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
        for target in LINK.findall(line):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or an anchor on the same page
            out.append((n, target, page.parent / target.split("#")[0]))
        for token in CODE.findall(line):
            token = token.rstrip(".,;:)")
            if re.search(r"[*<>{}]", token):
                continue  # a pattern, not a file
            if token.startswith(("../", "/", "~")):  # the docs write paths from the repository root
                out.append((n, token, Path(token).expanduser() if token[0] in "/~" else ROOT / token))
            elif "/" in token and token.endswith(FILE_EXT) and not token.startswith(MADE_BY_RUNS):
                out.append((n, token, ROOT / token))
            elif token.endswith(".md") and "/" not in token:  # a page beside this one, or at the root
                beside = page.parent / token
                out.append((n, token, beside if beside.exists() else ROOT / token))
    return out


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_reference_is_a_file_of_the_repository(page):
    """Issue 21, item 5: each page cites files of the repository only, and each of them exists."""
    bad = [f"{page.relative_to(ROOT)}:{n}: {ref} ({'outside the repository' if _outside(p) else 'no such file'})"
           for n, ref, p in references(page) if _outside(p) or not p.exists()]
    assert not bad, "\n".join(bad)


def test_the_checker_sees_what_it_must_refuse(tmp_path):
    """The check itself: a link to a missing page and a path outside the repository are both found."""
    page = tmp_path / "x.md"
    page.write_text("see [spec](spec.md), [gone](gone.md) and `../shared/SPEC.md`; `tests/test_docs_links.py`, "
                    "`/work/shared/SPEC.md`, `runs/quick/x.ckpt`, `configs/data/ood/<name>.yaml`, `README.md`")
    (tmp_path / "spec.md").write_text("")
    refs = {ref: p for _, ref, p in references(page)}
    assert set(refs) == {"spec.md", "gone.md", "../shared/SPEC.md", "tests/test_docs_links.py", "/work/shared/SPEC.md",
                         "README.md"}
    assert refs["spec.md"].exists() and refs["tests/test_docs_links.py"].exists() and not refs["gone.md"].exists()
    assert _outside(refs["../shared/SPEC.md"]) and _outside(refs["/work/shared/SPEC.md"])
    assert not _outside(refs["tests/test_docs_links.py"]) and refs["README.md"] == ROOT / "README.md"
