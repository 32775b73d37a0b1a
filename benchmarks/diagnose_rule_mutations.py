"""Mutation check of the diagnosis's selection rules (issue 13, item 9).

Each mutation (a flipped comparison, a threshold set to zero or disabled) is applied to a copy of
the repository in a temporary folder, and the rules tests (default ``tests/test_diagnose_rules.py``)
run there: every mutation must make them fail. Prints one line per mutation and the count.

    .venv/bin/python benchmarks/diagnose_rule_mutations.py [TEST_FILE ...]
"""
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

SRC = Path(__file__).resolve().parent.parent
MUT = [
    ("acceptance dBIC sign flipped", "otbot_hw/diagnose/rules.py", "return c.evidence < -ACCEPT_DBIC and not (c.dholdout > 0)", "return c.evidence > -ACCEPT_DBIC and not (c.dholdout > 0)"),
    ("ACCEPT_DBIC = 0", "otbot_hw/diagnose/rules.py", "ACCEPT_DBIC = 10.0", "ACCEPT_DBIC = 0.0"),
    ("held-out test dropped", "otbot_hw/diagnose/rules.py", "return c.evidence < -ACCEPT_DBIC and not (c.dholdout > 0)", "return c.evidence < -ACCEPT_DBIC"),
    ("residual-correlation deflation dropped", "otbot_hw/diagnose/rules.py", "return self.dbic / max(self.kappa, 1.0)", "return self.dbic"),
    ("SCREEN_DBIC = 0", "otbot_hw/diagnose/rules.py", "SCREEN_DBIC = 10.0", "SCREEN_DBIC = 0.0"),
    ("LATER_ROUND_FACTOR = 1", "otbot_hw/diagnose/rules.py", "LATER_ROUND_FACTOR = 5.0", "LATER_ROUND_FACTOR = 1.0"),
    ("SHORTLIST_FRACTION = 0", "otbot_hw/diagnose/rules.py", "SHORTLIST_FRACTION = 0.1", "SHORTLIST_FRACTION = 0.0"),
    ("MAX_CANDIDATES = 10", "otbot_hw/diagnose/rules.py", "MAX_CANDIDATES = 3", "MAX_CANDIDATES = 10"),
    ("AMBIGUOUS_DBIC = 0", "otbot_hw/diagnose/rules.py", "AMBIGUOUS_DBIC = 10.0", "AMBIGUOUS_DBIC = 0.0"),
    ("pair test sign flipped", "otbot_hw/diagnose/rules.py", "return (pair.dbic - first.dbic) / max(pair.kappa, 1.0) < -ACCEPT_DBIC", "return (pair.dbic - first.dbic) / max(pair.kappa, 1.0) > -ACCEPT_DBIC"),
    ("KAPPA_WHITE = 100", "otbot_hw/diagnose/rules.py", "KAPPA_WHITE = 1.2", "KAPPA_WHITE = 100.0"),
    ("nested-explanation rule dropped", "otbot_hw/diagnose/rules.py", "keep = [c for c in near if not any(set(o.parameters) < set(c.parameters) for o in near)]", "keep = near"),
    ("EXCESS_HELDOUT = 1e9", "otbot_hw/diagnose/adequacy.py", "EXCESS_HELDOUT = 0.5", "EXCESS_HELDOUT = 1e9"),
    ("TORQUE_FRACTION = 0", "otbot_hw/diagnose/significance.py", "TORQUE_FRACTION = 0.01", "TORQUE_FRACTION = 0.0"),
    ("HEADING_DRIFT = 0", "otbot_hw/diagnose/significance.py", "HEADING_DRIFT = 1.0", "HEADING_DRIFT = 0.0"),
    ("POSITION_DRIFT = 0", "otbot_hw/diagnose/significance.py", "POSITION_DRIFT = 0.05", "POSITION_DRIFT = 0.0"),
    ("LEVER_ARM = 0", "otbot_hw/diagnose/significance.py", "LEVER_ARM = 0.01", "LEVER_ARM = 0.0"),
    ("MISALIGNMENT = 0", "otbot_hw/diagnose/significance.py", "MISALIGNMENT = np.deg2rad(0.2)", "MISALIGNMENT = 0.0"),
    ("ODOMETRY_FRACTION = 0", "otbot_hw/diagnose/significance.py", "ODOMETRY_FRACTION = 0.002", "ODOMETRY_FRACTION = 0.0"),
    ("DELAY = 0", "otbot_hw/diagnose/significance.py", "DELAY = 1e-3", "DELAY = 0.0"),
    ("Z_MIN = 0", "otbot_hw/diagnose/significance.py", "Z_MIN = 2.0", "Z_MIN = 0.0"),
    ("EXCESS_FITTING = 1e9", "otbot_hw/diagnose/adequacy.py", "EXCESS_FITTING = 0.25", "EXCESS_FITTING = 1e9"),
    ("BOUND_FRACTION = 0", "otbot_hw/diagnose/adequacy.py", "BOUND_FRACTION = 1e-3", "BOUND_FRACTION = 0.0"),
    ("RELATIVE_SHIFT m_c = 1e9", "otbot_hw/diagnose/adequacy.py", '"m_c": 0.3', '"m_c": 1e9'),
    ("OFFSET_SHIFT = 1e9", "otbot_hw/diagnose/adequacy.py", 'OFFSET_SHIFT = {"x_B": 0.1, "y_B": 0.1}', 'OFFSET_SHIFT = {"x_B": 1e9, "y_B": 1e9}'),
]
tests = sys.argv[1:] or ["tests/test_diagnose_rules.py"]
dst = Path(tempfile.mkdtemp(prefix="rule-mutations-")) / "repo"
results = []
for label, rel, old, new in MUT:
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(SRC, dst, ignore=shutil.ignore_patterns(".git", "__pycache__", "*.mcap", "otbot-*", ".venv"))
    f = dst / rel
    text = f.read_text()
    assert text.count(old) == 1, (label, text.count(old))
    f.write_text(text.replace(old, new))
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests], cwd=dst,
                       env={**os.environ, "PYTHONPATH": str(dst)}, capture_output=True, text=True)
    last = [l for l in r.stdout.splitlines() if l.strip()][-1]
    failed = [l.split("::")[1].split(" ")[0] for l in r.stdout.splitlines() if l.startswith("FAILED")]
    results.append((label, r.returncode != 0, failed, last))
    print(f"{'CAUGHT' if r.returncode else 'MISSED'}  {label}: {failed} ({last})", flush=True)
shutil.rmtree(dst.parent, ignore_errors=True)
print(f"{sum(c for _, c, _, _ in results)}/{len(results)} mutations caught")
sys.exit(0 if all(c for _, c, _, _ in results) else 1)
