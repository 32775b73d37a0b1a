"""Module size (issue 19): no ``.py`` file under ``otbot_hw/``, ``drivers/`` or ``sim/`` over ``MAX_LINES`` lines
unless its module docstring says why, on a line starting ``Length:``.

``ALLOWED`` lists the files other branches were still splitting when this test was written, each with the
branch that owns it; remove an entry once that branch has landed (a stale entry fails the test too).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("otbot_hw", "drivers", "sim")
MAX_LINES = 400

#: Known debt: files over MAX_LINES without a "Length:" reason, and the branch splitting them.
ALLOWED: dict[str, str] = {
}


def length_problem(path: Path, max_lines: int = MAX_LINES) -> str | None:
    """Why ``path`` is too long (its line count, no ``Length:`` line in its module docstring), or None."""
    text = path.read_text()
    n = len(text.splitlines())
    if n <= max_lines:
        return None
    doc = ast.get_docstring(ast.parse(text, str(path))) or ""
    if any(line.strip().startswith("Length:") for line in doc.splitlines()):
        return None
    return f"{n} lines (> {max_lines}) and no line starting 'Length:' in its module docstring"


def files() -> list[Path]:
    return sorted(p for pk in PACKAGES for p in (ROOT / pk).rglob("*.py"))


@pytest.mark.parametrize("path", files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_long_module_without_a_reason(path):
    rel = path.relative_to(ROOT).as_posix()
    if rel in ALLOWED:
        return
    problem = length_problem(path)
    assert problem is None, (f"{rel}: {problem}: split it into named parts (one concept per module) or say "
                             "why not in its docstring")


def test_allowed_entries_are_still_needed():
    stale = [f"{rel} ({branch})" for rel, branch in ALLOWED.items()
             if not (ROOT / rel).exists() or length_problem(ROOT / rel) is None]
    assert not stale, f"gone, short enough or stating their reason: remove from ALLOWED: {stale}"


def test_the_checker_sees_a_long_module_and_its_reason(tmp_path):
    body = "x = 1\n" * MAX_LINES
    long = tmp_path / "long.py"
    long.write_text('"""A module."""\n' + body)
    reasoned = tmp_path / "reasoned.py"
    reasoned.write_text('"""A module.\n\nLength: one state machine.\n"""\n' + body)
    short = tmp_path / "short.py"
    short.write_text('"""A module."""\n' + "x = 1\n" * (MAX_LINES - 1))
    not_doc = tmp_path / "not_doc.py"
    not_doc.write_text('"""A module."""\n# Length: a comment is not the docstring\n' + body)
    assert "401 lines" in length_problem(long)
    assert length_problem(reasoned) is None and length_problem(short) is None
    assert length_problem(not_doc) is not None
