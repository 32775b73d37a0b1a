"""The one check of a folder a program creates a file in but never creates itself (README, Output paths:
the daemon's socket folder and recording folder): it exists, is a folder, and this user may write in it.
Each caller words its own messages."""
from __future__ import annotations

import os
from pathlib import Path


def require_folder(folder: Path, error: type[Exception], missing: str, not_a_folder: str, not_writable: str) -> Path:
    """``folder`` if this process can create a file in it, else ``error`` raised with the message of what is
    wrong: ``missing``, ``not_a_folder``, or ``not_writable`` (the effective user lacks write or search
    permission)."""
    folder = Path(folder)
    if not folder.exists():
        raise error(missing)
    if not folder.is_dir():
        raise error(not_a_folder)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise error(not_writable)
    return folder
