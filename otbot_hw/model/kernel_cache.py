"""Where numba keeps the project's compiled kernels: one folder per version of their sources.

numba's on-disk cache keys a compiled function by its own source file only. A kernel that inlines or
calls a compiled function from another file (``kinematics.fik_entries`` in the EKF kernels,
``effect_physics.forces_active`` in the integrators) keeps the old callee after that file changes, until
its own file changes too: a stale, silently wrong kernel. Keying the cache folder by a hash of every
file that defines compiled kernels (``KERNEL_SOURCES``) makes any change to any of them start a fresh
cache; unchanged sources reuse theirs.

The folder is ``$NUMBA_CACHE_DIR/otbot-<hash>`` when the user set ``NUMBA_CACHE_DIR``, else
``$XDG_CACHE_HOME/otbot/numba/<hash>`` (``~/.cache/otbot/numba/<hash>``). When it cannot be written,
numba falls back to its own ``__pycache__`` folders. ``configure()`` runs from ``otbot_hw.model``'s
package import, before any kernel is decorated (every compiled module imports ``otbot_hw.model``
first; ``tests/test_kernel_cache.py`` checks both lists).
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: Every file (relative to the ``otbot_hw`` package) that defines numba-compiled kernels.
KERNEL_SOURCES: tuple[str, ...] = (
    "model/compiled.py", "model/effect_physics.py", "model/kinematics.py",
    "model/sensor_model.py", "model/slip_law.py", "identification/model.py", "control/prediction.py",
    "control/task_model.py", "estimation/kernels.py", "estimation/imu_cycle.py", "estimation/payload.py",
    "simulation/sensing.py", "simulation/integrators.py", "diagnose/residuals.py",
)

_configured: str | None = None


def sources_hash(root: Path | None = None) -> str:
    """16 hex digits of the SHA-256 over the kernel sources' paths and contents (a missing file counts
    as empty)."""
    root = root if root is not None else Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    for rel in KERNEL_SOURCES:
        h.update(rel.encode())
        try:
            h.update((root / rel).read_bytes())
        except OSError:
            h.update(b"\0missing")
    return h.hexdigest()[:16]


def cache_folder(environ=os.environ) -> str:
    """The cache folder for the current kernel sources (see the module docstring)."""
    key = sources_hash()
    user = environ.get("NUMBA_CACHE_DIR")
    if user:
        return os.path.join(user, f"otbot-{key}")
    base = environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "otbot", "numba", key)


def configure() -> str:
    """Point numba's cache at ``cache_folder()`` (once per process); returns the folder."""
    global _configured
    if _configured is None:
        from numba.core import config

        _configured = cache_folder()
        config.CACHE_DIR = _configured
    return _configured
