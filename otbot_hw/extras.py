"""Optional dependencies, installed as pip extras, imported only by the commands that use them.

The on-robot install (``pip install otbot-hw``) carries what the daemon, the drivers, the
simulator, identification and the diagnosis use. Three heavier libraries are extras:

* ``planner``: CasADi + IPOPT for ``otbot plan`` and the ``planned`` tracking scenario;
* ``cluster``: Dask ``distributed`` for ``--scheduler`` (sweeps and fleet diagnoses on a cluster);
* ``ros2``: ``rosbags`` for ROS 2 bag import/export.

``pip install 'otbot-hw[dev]'`` (README's Quick start) installs all of them. A command that needs a
missing extra stops with one line naming the extra to install (exit 2), never a traceback.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: module -> (extra, what needs it)
EXTRAS = {
    "casadi": ("planner", "the trajectory planner (otbot plan, the 'planned' scenario)"),
    "distributed": ("cluster", "a Dask cluster (--scheduler)"),
    "rosbags": ("ros2", "ROS 2 bags (otbot import / otbot export --ros2)"),
}


class MissingExtraError(RuntimeError):
    """An optional dependency is not installed (bad set-up: exit 2 with the install command)."""


def require(module: str) -> ModuleType:
    """Import ``module`` (a key of ``EXTRAS``, or a submodule of one) or raise ``MissingExtraError``."""
    root = module.split(".")[0]
    extra, purpose = EXTRAS[root]
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(f"{purpose} needs the '{extra}' extra, which is not installed "
                                f"({exc}): pip install 'otbot-hw[{extra}]'") from None
