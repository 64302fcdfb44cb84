"""The documents keep up with the repository: every script is named in scripts/README.md, and
every figure in docs/ is shown by a document and exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_script_is_named_in_the_scripts_readme() -> None:
    text = (ROOT / "scripts" / "README.md").read_text()
    scripts = sorted(p.relative_to(ROOT / "scripts") for p in (ROOT / "scripts").rglob("*.py"))
    assert scripts
    missing = [str(p) for p in scripts if f"`{p}" not in text]
    assert missing == []


def test_every_figure_in_docs_is_shown_and_every_shown_figure_exists() -> None:
    documents = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    shown = {
        (path.parent / link).resolve()
        for path in documents
        for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", path.read_text())
    }
    figures = {p.resolve() for ext in ("png", "gif") for p in (ROOT / "docs").glob(f"*.{ext}")}
    assert figures - shown == set()
    assert [p for p in shown if not p.exists()] == []
