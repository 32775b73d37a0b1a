"""The one check of a folder a program creates a file in but never creates itself (README, Output paths:
the daemon's socket folder and recording folder): it exists, is a folder, and this user may write in it.
Each caller words its own message from the reason."""
from __future__ import annotations

import os
from pathlib import Path

MISSING, NOT_A_FOLDER, NOT_WRITABLE = "missing", "not a folder", "not writable"


def folder_problem(folder: Path) -> str | None:
    """Why this process cannot create a file in ``folder`` (``MISSING``, ``NOT_A_FOLDER``, ``NOT_WRITABLE``:
    the effective user lacks write or search permission), or None when it can."""
    folder = Path(folder)
    if not folder.exists():
        return MISSING
    if not folder.is_dir():
        return NOT_A_FOLDER
    if not os.access(folder, os.W_OK | os.X_OK):
        return NOT_WRITABLE
    return None
