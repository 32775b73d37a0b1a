"""What the bench makes of a session's recordings: the step's identification (``identify``: the passed
steps' recordings and this step's, fitted by ``identification.session.identify_session``), the geometry
refitted when a step's gates fail (``geometry_mismatch``), and the mismatch finder on the session
(``diagnose_session``, as ``otbot diagnose`` runs it). Used by ``procedure``.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

from otbot_hw.identification.errors import IdentificationError
from otbot_hw.identification.uncertainty import robot_params
from otbot_hw.params import OtbotParams
from otbot_hw.recording import read_recording
from otbot_hw.runtime.bench.session import SessionFolder
from otbot_hw.runtime.bench.steps import BENCH_STEPS


def step_recordings(session: SessionFolder, steps: list[str], step: str, recording: Path) -> dict[str, list]:
    """The recordings a fit of ``step`` uses, by step: ``recording`` for ``step``, the accepted ones of
    the steps passed so far."""
    recs: dict[str, list] = {}
    for s in steps:
        paths = [recording] if s == step else session.accepted_recordings(s)
        if paths and (s == step or session.status(s) == "passed"):
            recs[s] = [read_recording(p) for p in paths]
    return recs


def identify(recs: dict[str, list], start: OtbotParams, specs: dict, known_std: dict[str, float]):
    """``identify_session`` on ``recs`` (``step_recordings``) with each step's excitation ``specs``."""
    from otbot_hw.identification.session import identify_session

    return identify_session(recs, start, specs=specs, known_std=known_std)


def geometry_mismatch(recs: dict[str, list], start: OtbotParams, file_params: OtbotParams, specs: dict,
                      known_std: dict[str, float]) -> str | None:
    """When a step's gates fail, the last parameters the bench takes from the file are the geometry (l1,
    l2, r): the session refitted with them free too. If that explains every recording, the sentences
    naming each one that moved from ``file_params`` by more than 3 std; else None (the diagnosis looks for
    missing physics)."""
    from otbot_hw.identification.session import identify_session
    from otbot_hw.identification.uncertainty import NUISANCE_PARAMS

    try:
        res = identify_session(recs, start, specs=specs, known_std=known_std,
                               nuisance=NUISANCE_PARAMS + ("l1", "l2", "r"))
    except IdentificationError:
        return None
    if not res.passed:
        return None
    std = res.std
    off = [f"{n} {getattr(file_params, n):.4g} m in the file, estimated {res.values[n]:.4g} +- {std[n]:.2g} m"
           for n in ("l1", "l2", "r") if std.get(n, 0) > 0
           and abs(res.values[n] - getattr(file_params, n)) > 3 * std[n]]
    return "; ".join(off) or None


def diagnose_session(session: SessionFolder, steps: list[str], values: dict, start: OtbotParams,
                     extra: dict[str, list[Path]] | None = None, say: Callable[[str], None] = lambda m: None) -> dict:
    """The mismatch finder on the session's recordings (the passed steps', and ``extra`` per step):
    the unloaded robot's steps with the identified unloaded robot (``values``, session symbols, on
    ``start``), the platform step with the loaded one. Written to ``diagnosis.json`` too."""
    from otbot_hw.diagnose.data import from_recording
    from otbot_hw.diagnose.diagnosis import diagnose

    out: dict[str, Any] = {}
    groups = {"unloaded": [s for s in steps if not BENCH_STEPS[s].loaded],
              "loaded": [s for s in steps if BENCH_STEPS[s].loaded]}
    for label, group in groups.items():
        paths = [p for s in group for p in [*session.accepted_recordings(s), *(extra or {}).get(s, [])]]
        if not paths:
            continue
        say(f"[bench] diagnose: the {label} robot's recordings ({', '.join(session.rel(p) for p in paths)})")
        data = [from_recording(read_recording(p), name=session.rel(p)) for p in paths]
        params = robot_params(values, start, loaded=label == "loaded")
        out[label] = diagnose(data, params, progress=lambda m: say(m))
    effects = sorted({e["name"] for d in out.values() for e in d["effects"]})
    ambiguous = [c["name"] for d in out.values() for g in d["ambiguous"] for c in g["candidates"]]
    out["effects"] = effects
    out["verdict"] = ("missing physics: " + ", ".join(effects) if effects else
                      ("ambiguous: " + " / ".join(ambiguous) if ambiguous else
                       "no missing physics found: no catalog effect improves the model by the evidence threshold"))
    (session.path / "diagnosis.json").write_text(json.dumps(out, indent=1, allow_nan=False))
    return out
