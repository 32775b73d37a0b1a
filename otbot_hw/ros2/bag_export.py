"""A project recording as a rosbag2 folder (``otbot export RUN.mcap --ros2 OUT``).

The bag is written into a temporary folder next to ``OUT`` and renamed into place when complete,
so an error or a crash never leaves a half-written ``OUT``. Layout: ``otbot_hw.ros2.writer``.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from otbot_hw.recording import Recording, write_samples_and_events
from otbot_hw.ros2 import BagError
from otbot_hw.ros2.writer import BagWriter


def check_output(out: Path) -> None:
    """BagError unless ``out`` can become the bag folder: absent (its parent a writable folder),
    an empty folder or an earlier rosbag2 folder (holding ``metadata.yaml``: replaced)."""
    out = Path(out)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise BagError(f"--ros2 {out}: folder {parent} does not exist (otbot creates no parent folders)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise BagError(f"--ros2 {out}: cannot write in folder {parent}")
    if out.exists():
        if not out.is_dir():
            raise BagError(f"--ros2 {out}: exists and is not a folder (a rosbag2 bag is a folder)")
        if any(out.iterdir()) and not (out / "metadata.yaml").is_file():
            raise BagError(f"--ros2 {out}: is a folder that holds files but no metadata.yaml (not a bag); "
                           "otbot replaces only an earlier bag or an empty folder")


def export_recording(rec: Recording, out: str | Path) -> dict:
    """Write ``rec`` as the rosbag2 folder ``out``; returns {topics: {name: [type, count]}, path,
    mcap, noise_source}. An existing bag at ``out`` is replaced only once the new one is complete."""
    out = Path(out)
    check_output(out)
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    if tmp.exists():
        shutil.rmtree(tmp)
    topics = [tp for tp in rec.channels()]
    try:
        with BagWriter(tmp, rec.metadata, topics, flush_every=1000, has_force=rec.truth_force is not None,
                       has_gyro_bias=rec.estimate_gyro_bias is not None, name=out.name) as w:
            write_samples_and_events(w, rec)
        # the new bag is complete: put it in place (renamed, the old one removed after)
        old = None
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except ValueError as exc:  # the recording cannot be a bag (e.g. negative sample times)
        shutil.rmtree(tmp, ignore_errors=True)
        raise BagError(f"--ros2 {out}: {exc}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"path": str(out), "mcap": str(out / w.path.name), "noise_source": w.noise_source,
            "topics": {tp: [ty, w.counts[tp]] for tp, ty in w.types.items()}, "samples": len(rec)}
