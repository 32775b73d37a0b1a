"""Import rules of the layout (README, Layout): arrows point down.

* ``otbot_hw/model`` imports nothing of the project above it (only ``otbot_hw.model`` and
  ``otbot_hw.params``);
* the library (``otbot_hw/``) imports neither ``sim`` (simulated hardware) nor ``drivers``,
  except in ``otbot_hw/cli`` and ``otbot_hw/runtime``, which wire back ends together;
* ``drivers`` never imports ``sim`` (the real robot does not know the simulated one);
* no import cycle among the project's modules (``otbot_hw``, ``sim``, ``drivers``);
* outside ``sim/`` and the tests, no attribute probe (``getattr``/``hasattr`` with a literal name) of a
  member only simulated robots have (``plant``, ``truth_force``, ...): a capability is declared, not
  guessed (the known-debt list of offenders is empty).

Every import is checked, including those inside functions.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
WIRING = ("otbot_hw/cli/", "otbot_hw/runtime/")


PACKAGES = ("otbot_hw", "sim", "drivers")
#: Members only simulated robots have: probing a Robot for them guesses a capability.
SIMULATED_ONLY = ("plant", "truth_force", "stepper", "sensors", "t_plant", "inject_fault", "operator", "report")
#: Known debt: (file, member) probes of simulated-only members outside sim/ and tests. Empty since the
#: ``SimulatedRobot`` interface declares them (issue 19 item 2); a probe not listed fails the test.
KNOWN_PROBES: set[tuple[str, str]] = set()


def module_name(path: Path, root: Path = ROOT) -> str:
    """Dotted module name of ``path`` under ``root`` (a package's ``__init__`` is the package)."""
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, root: Path = ROOT, known=()) -> list[tuple[int, str]]:
    """(line, module) of every import statement in ``path`` (relative imports resolved), also those
    inside functions. ``from pkg import name`` gives ``pkg.name`` when that is a module in ``known``."""
    tree = ast.parse(path.read_text(), str(path))
    me = module_name(path, root)
    pkg = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([mod] if mod else []))
            subs = [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in known]
            out += [(node.lineno, m) for m in subs] or [(node.lineno, mod)]
    return out


def import_graph(root: Path = ROOT, packages=PACKAGES) -> dict[str, set[str]]:
    """Module -> the project modules it imports (anywhere in its body)."""
    paths = {module_name(p, root): p for pk in packages for p in (root / pk).rglob("*.py")}
    return {m: {t for _, t in imports(p, root, paths) if t in paths and t != m} for m, p in paths.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles: strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, stack, on, out, n = {}, {}, [], set(), [], 0
    for start in graph:
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = n
        n += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = n
                    n += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def simulated_probes(path: Path) -> list[tuple[int, str]]:
    """(line, member) of ``getattr(x, "member"...)`` / ``hasattr(x, "member")`` of a simulated-only member."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in ("getattr", "hasattr")
                and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                and node.args[1].value in SIMULATED_ONLY):
            out.append((node.lineno, node.args[1].value))
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
    """The rule checker itself: an import inside a function is found (the probe file in tmp_path)."""
    f = tmp_path / "otbot_hw" / "_layering_probe.py"
    f.parent.mkdir()
    f.write_text("def g():\n    from sim.plant import Plant\n    return Plant\n")
    assert (2, "sim.plant") in imports(f, tmp_path)


def test_no_import_cycle():
    found = cycles(import_graph())
    assert not found, f"import cycles (function-local imports included): {found}"


def test_the_cycle_checker_sees_a_cycle_through_a_function_local_import(tmp_path):
    """a imports b at the top, b imports a inside a function (the shape dynamics <-> task_space had), and
    ``from pkg import module`` counts as importing the module."""
    pkg = tmp_path / "otbot_hw"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from otbot_hw.b import f\n")
    (pkg / "b.py").write_text("def f():\n    from otbot_hw import a\n    return a\n")
    (pkg / "c.py").write_text("from otbot_hw import a\n")
    assert cycles(import_graph(tmp_path, ("otbot_hw",))) == [["otbot_hw.a", "otbot_hw.b"]]


@pytest.mark.parametrize("path", [p for p in files("otbot_hw") + files("drivers")], ids=lambda p: str(p.relative_to(ROOT)))
def test_no_new_probe_of_simulated_only_members(path):
    rel = path.relative_to(ROOT).as_posix()
    new = [(ln, m) for ln, m in simulated_probes(path) if (rel, m) not in KNOWN_PROBES]
    assert not new, (f"{rel} probes a Robot for simulated-only members {new}: declare the capability "
                     "(a simulated-robot interface) instead of getattr/hasattr")


def test_the_probe_checker_sees_a_probe(tmp_path):
    f = tmp_path / "probe.py"
    f.write_text("def g(robot):\n    return getattr(robot, 'plant', None), hasattr(robot, 'truth_force'), "
                 "getattr(robot, 'period')\n")
    assert simulated_probes(f) == [(2, "plant"), (2, "truth_force")]
