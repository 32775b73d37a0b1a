"""A bench session's folder: every recording, the bus logs, and ``session.json``, its manifest.

Layout (``docs/identification.md``, section *The bench procedure*)::

    SESSION/session.json            manifest: robot identity, settings, per step its attempts
    SESSION/<step>-<n>.mcap         the excitation of attempt n (project recording format)
    SESSION/checks/<step>-<n>-rest.mcap, <step>-<n>-probe.mcap   the runs of the checks
    SESSION/bus-<k>.blf             raw bus log of the k-th invocation (python-can BLF)
    SESSION/designs/*.json          designed excitations used
    SESSION/params.yaml, report/, diagnosis.json   outputs (defaults of --out, --report)

The manifest is rewritten after every change (atomically: a temporary file renamed), so an
abort, a fault or a crash leaves a session that ``--resume`` continues at the first step not
passed. Nothing already recorded is ever overwritten: attempt numbers only grow.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from otbot_hw.runtime.bench.steps import SimulatedRobot

FORMAT = "otbot-bench-session"
VERSION = 1
STATUSES = ("pending", "passed", "redo", "aborted", "failed")


class SessionError(ValueError):
    """A session folder that cannot be used (bad input): missing, not a session, another robot."""


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S%z")


class SessionFolder:
    """The folder of one bench session and its manifest (``data``, a JSON-ready dict)."""

    def __init__(self, path: Path, data: dict):
        self.path = Path(path)
        self.data = data

    # -- creation / resumption ---------------------------------------------------------------------
    @classmethod
    def create(cls, path: Path, identity: dict, settings: dict) -> "SessionFolder":
        """A new session in ``path`` (created; its parent must exist; an existing folder must be empty)."""
        path = Path(path)
        if path.exists() and (not path.is_dir() or any(path.iterdir())):
            what = "a session already" if (path / "session.json").is_file() else "files"
            raise SessionError(f"--session {path}: the folder holds {what}; continue a session with --resume "
                               f"{path}, or name a new folder")
        path.mkdir(exist_ok=True)
        s = cls(path, {"format": FORMAT, "version": VERSION, "created": _now(), "robot": identity,
                       "settings": settings, "steps": {st: {"status": "pending", "attempts": []}
                                                       for st in settings["steps"]},
                       "invocations": []})
        s.save()
        return s

    @classmethod
    def open(cls, path: Path) -> "SessionFolder":
        """An existing session (``--resume``); ``SessionError`` if it is not one."""
        path = Path(path)
        f = path / "session.json"
        if not path.is_dir():
            raise SessionError(f"--resume {path}: no such session folder")
        if not f.is_file():
            raise SessionError(f"--resume {path}: not a bench session (no session.json)")
        try:
            data = json.loads(f.read_text())
        except (OSError, ValueError) as exc:
            raise SessionError(f"--resume {path}: session.json cannot be read: {exc}") from None
        if not isinstance(data, dict) or data.get("format") != FORMAT or not isinstance(data.get("steps"), dict):
            raise SessionError(f"--resume {path}: session.json is not a bench session manifest")
        if data.get("version") != VERSION:
            raise SessionError(f"--resume {path}: session format version {data.get('version')!r}, this otbot reads "
                               f"{VERSION}")
        return cls(path, data)

    def check_robot(self, identity: dict) -> None:
        """``SessionError`` naming the difference when ``identity`` is not the session's robot."""
        mine = self.data.get("robot") or {}
        diffs = []
        if mine.get("bus") != identity.get("bus"):
            diffs.append(f"bus {mine.get('bus')!r} vs {identity.get('bus')!r}")
        for name, node in (mine.get("nodes") or {}).items():
            other = (identity.get("nodes") or {}).get(name)
            if other is None:
                diffs.append(f"{name} missing")
                continue
            for k in ("node_id", "vendor", "product", "serial"):
                if node.get(k) != other.get(k):
                    diffs.append(f"{name} {k} {node.get(k)!r} vs {other.get(k)!r}")
        if mine.get("simulated") != identity.get("simulated"):
            a, b = mine.get("simulated") or {}, identity.get("simulated") or {}
            diffs.append(f"simulated robot {a.get('label', a)!r} vs {b.get('label', b)!r}")
        if diffs:
            raise SessionError(f"session {self.path} was recorded on another robot ({'; '.join(diffs[:4])}): resume it "
                               "on the robot it was started with (the same --sim-params and --sim-load when "
                               "simulated), or start a new session")

    # -- manifest ----------------------------------------------------------------------------------
    def save(self) -> None:
        tmp = self.path / ".session.json.tmp"
        tmp.write_text(json.dumps(self.data, indent=1, allow_nan=False, default=_jsonable))
        os.replace(tmp, self.path / "session.json")

    @property
    def settings(self) -> dict:
        return self.data["settings"]

    def step(self, name: str) -> dict:
        return self.data["steps"][name]

    def status(self, name: str) -> str:
        return self.step(name)["status"]

    def begin_invocation(self, note: dict) -> int:
        inv = self.data["invocations"]
        inv.append({"started": _now(), **note})
        self.save()
        return len(inv)

    def end_invocation(self, **note) -> None:
        if self.data["invocations"]:
            self.data["invocations"][-1].update(ended=_now(), **note)
            self.save()

    # -- attempts and recordings -------------------------------------------------------------------
    def new_attempt(self, step: str) -> dict:
        """Attempt n + 1 of ``step`` (numbers never reused), with its recording paths (relative)."""
        atts = self.step(step)["attempts"]
        n = 1 + max((a["attempt"] for a in atts), default=0)
        a = {"attempt": n, "started": _now(), "status": "pending", "checks": [], "recording": None,
             "check_recordings": [], "reasons": []}
        atts.append(a)
        self.save()
        return a

    def recording_path(self, step: str, attempt: int, kind: str | None = None) -> Path:
        if kind is None:
            return self.path / f"{step}-{attempt}.mcap"
        (self.path / "checks").mkdir(exist_ok=True)
        return self.path / "checks" / f"{step}-{attempt}-{kind}.mcap"

    def rel(self, p: Path) -> str:
        return str(Path(p).relative_to(self.path))

    def set_status(self, step: str, status: str, attempt: dict | None = None, reasons: list[str] | None = None,
                   **extra: Any) -> None:
        assert status in STATUSES
        st = self.step(step)
        st["status"] = status
        if attempt is not None:
            attempt["status"] = status
            if reasons is not None:
                attempt["reasons"] = list(reasons)
            attempt.update(extra)
        self.save()

    def accepted_recordings(self, step: str) -> list[Path]:
        """The recording(s) a passed step was identified from (its last passed attempt)."""
        st = self.step(step)
        for a in reversed(st["attempts"]):
            if a["status"] == "passed" and a.get("recording"):
                return [self.path / a["recording"]]
        return []

    def all_recordings(self) -> list[str]:
        out = []
        for st in self.data["steps"].values():
            for a in st["attempts"]:
                out += [r for r in [a.get("recording"), *a.get("check_recordings", [])] if r]
        return out


def _jsonable(o):
    import numpy as np

    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def identity(robot, bus: str, sim: SimulatedRobot | None = None, sim_label: str | None = None) -> dict:
    """Who the robot is: each node's CiA 301 identity object 0x1018 (vendor, product, revision, serial)
    read over SDO, and for a simulated robot a fingerprint of its parameters, effects and load."""
    import hashlib

    out: dict[str, Any] = {"bus": bus, "nodes": robot.node_identities(), "simulated": None}
    if sim is not None:
        blob = json.dumps({"params": sim.unloaded.values(), "effects": sim.effects, "load": sim.load}, sort_keys=True)
        out["simulated"] = {"sha": hashlib.sha256(blob.encode()).hexdigest()[:16], "label": sim_label or "simulated"}
    return out
