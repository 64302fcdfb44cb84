"""The documents keep up with the repository: every script is named in scripts/README.md, every
research script makes a figure of the results or is run by a test, every figure in docs/ is
shown by a document and exists, every module of the package is named in
docs/ARCHITECTURE.md and nothing else there, the documents and the modules keep their sizes,
and the README sets up within its first screen."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_script_is_named_in_the_scripts_readme() -> None:
    text = (ROOT / "scripts" / "README.md").read_text()
    scripts = sorted(p.relative_to(ROOT / "scripts") for p in (ROOT / "scripts").rglob("*.py"))
    assert scripts
    missing = [str(p) for p in scripts if f"`{p}" not in text]
    assert missing == []


def test_every_research_script_makes_a_figure_of_the_results_or_is_run_by_a_test() -> None:
    """A script stays in scripts/research/ while docs/RESULTS.md or docs/PERFORMANCE.md names it
    (a figure there comes from it) or a test other than this one runs it."""
    docs = "".join((ROOT / "docs" / name).read_text() for name in ("RESULTS.md", "PERFORMANCE.md"))
    tests = "".join(
        p.read_text() for p in sorted((ROOT / "tests").glob("*.py")) if p.name != "test_docs.py"
    )
    scripts = sorted((ROOT / "scripts" / "research").glob("*.py"))
    assert scripts
    named = (f"research/{p.stem}" in docs or p.name in docs or p.name in tests for p in scripts)
    assert [p.name for p, ok in zip(scripts, named, strict=True) if not ok] == []


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


PACKAGE = ROOT / "lolgps_torch"
MODULE_LINES = 450
# A module over MODULE_LINES lines is allowed only where its docstring says why it is kept whole.
LONG_MODULES = {"robot/rigid_body.py": "kept together"}


def package_modules() -> list[str]:
    """Every module of the package by its path in it (``sim/world.py``), ``__init__`` excepted."""
    return sorted(
        str(p.relative_to(PACKAGE)) for p in PACKAGE.rglob("*.py") if p.name != "__init__.py"
    )


def lines(path: Path) -> int:
    return len(path.read_text().splitlines())


def test_every_module_is_named_in_the_architecture() -> None:
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    modules = package_modules()
    assert modules
    missing = [m for m in modules if f"`{m}`" not in text]
    assert missing == []


def test_the_architecture_names_no_module_that_does_not_exist() -> None:
    """A ``*.py`` path in ARCHITECTURE is a module of the package (``sim/world.py``) or a file of
    the repository (``scripts/run_stream.py``)."""
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    named = set(re.findall(r"(?<![\w/.])([\w/]+\.py)\b", text))
    assert named
    absent = sorted(n for n in named if not (PACKAGE / n).is_file() and not (ROOT / n).is_file())
    assert absent == []


def test_results_has_at_most_400_lines() -> None:
    assert lines(ROOT / "docs" / "RESULTS.md") <= 400


def test_history_has_at_most_300_lines() -> None:
    assert lines(ROOT / "docs" / "HISTORY.md") <= 300


def readme_setup_line() -> int:
    """The line (from 1) of the README's set-up: the first command line that runs ``pip install``,
    in a fenced block or an indented one."""
    fenced = False
    for number, line in enumerate((ROOT / "README.md").read_text().splitlines(), start=1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        command = fenced or line.startswith(("    ", "\t"))
        if command and "pip install" in line:
            return number
    raise AssertionError("README.md has no set-up command (a code line with `pip install`)")


def test_the_readme_sets_up_within_its_first_40_lines() -> None:
    assert readme_setup_line() <= 40


def long_modules() -> list[str]:
    """The modules over MODULE_LINES lines, except those whose docstring says why."""
    over = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = str(path.relative_to(PACKAGE))
        if lines(path) <= MODULE_LINES:
            continue
        why = LONG_MODULES.get(module)
        docstring = ast.get_docstring(ast.parse(path.read_text())) or ""
        if why is None or why not in docstring or f"{MODULE_LINES} lines" not in docstring:
            over.append(f"{module} ({lines(path)})")
    return over


def test_the_long_modules_say_why() -> None:
    """Only the modules LONG_MODULES names may pass MODULE_LINES lines, and their docstring says
    why; this test holds them to it whatever the other modules' sizes."""
    for module in LONG_MODULES:
        docstring = ast.get_docstring(ast.parse((PACKAGE / module).read_text())) or ""
        assert LONG_MODULES[module] in docstring and f"{MODULE_LINES} lines" in docstring


def test_every_module_has_at_most_450_lines() -> None:
    assert long_modules() == []
