"""Import rules of the layout (README, Layout): arrows point down.

* ``otbot_hw/model`` imports nothing of the project above it (only ``otbot_hw.model`` and
  ``otbot_hw.params``);
* the library (``otbot_hw/``) imports neither ``sim`` (simulated hardware) nor ``drivers``,
  except in ``otbot_hw/cli`` and ``otbot_hw/runtime``, which wire back ends together;
* ``drivers`` never imports ``sim`` (the real robot does not know the simulated one).

Every import is checked, including those inside functions.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
WIRING = ("otbot_hw/cli/", "otbot_hw/runtime/")


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import statement in ``path`` (relative imports resolved)."""
    tree = ast.parse(path.read_text(), str(path))
    pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([mod] if mod else []))
            out.append((node.lineno, mod))
    return out


def files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def top(module: str) -> str:
    return module.split(".")[0]


def test_the_rules_see_every_package():
    assert files("otbot_hw/model") and files("otbot_hw/simulation") and files("drivers") and files("sim")


@pytest.mark.parametrize("path", files("otbot_hw/model"), ids=lambda p: str(p.relative_to(ROOT)))
def test_model_imports_nothing_above_it(path):
    bad = [(ln, m) for ln, m in imports(path)
           if top(m) in ("otbot_hw", "sim", "drivers")
           and not (m.startswith("otbot_hw.model") or m == "otbot_hw.params" or m == "otbot_hw")]
    assert not bad, f"{path.relative_to(ROOT)} imports above the model: {bad}"


@pytest.mark.parametrize("path", files("otbot_hw"), ids=lambda p: str(p.relative_to(ROOT)))
def test_library_knows_no_back_end(path):
    rel = path.relative_to(ROOT).as_posix()
    if rel.startswith(WIRING):
        return
    bad = [(ln, m) for ln, m in imports(path) if top(m) in ("sim", "drivers")]
    assert not bad, f"{rel} imports a back end (only {', '.join(WIRING)} may): {bad}"


@pytest.mark.parametrize("path", files("drivers"), ids=lambda p: str(p.relative_to(ROOT)))
def test_drivers_do_not_know_the_simulated_robot(path):
    bad = [(ln, m) for ln, m in imports(path) if top(m) == "sim"]
    assert not bad, f"{path.relative_to(ROOT)} imports the simulated robot: {bad}"


def test_the_checker_catches_a_violation(tmp_path):
    """The rule checker itself: an import inside a function is found."""
    f = ROOT / "otbot_hw" / "_layering_probe.py"
    try:
        f.write_text("def g():\n    from sim.plant import Plant\n    return Plant\n")
        assert (2, "sim.plant") in imports(f)
    finally:
        f.unlink()
