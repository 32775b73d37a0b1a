"""Many recordings diagnosed in parallel (a fleet's day of runs), each on its own.

``diagnose_each`` runs one diagnosis per recording in worker processes
(``concurrent.futures.ProcessPoolExecutor``). Phase B moves this onto the shared
identification executor (local processes by default, Dask distributed with a scheduler
address); the unit of work stays ``_one(path, params_path, holdout_paths)``.
"""
from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path


def _one(path: str, params_path: str | None, holdout: list[str]) -> dict:
    from otbot_hw.diagnose.data import load
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.params import OtbotParams, nominal
    from otbot_hw.recording import RecordingError

    params = OtbotParams.load(params_path) if params_path else nominal()
    try:
        recs = load([path])
        held = load(holdout)
    except RecordingError as exc:
        return {"recording": path, "error": str(exc)}
    r = diagnose(recs, params, held)
    r["recording"] = path
    return r


def diagnose_each(paths: list[Path], params_path: Path | None = None, holdout: list[Path] | None = None,
                  workers: int = 2, progress=lambda msg: None) -> list[dict]:
    """One diagnosis per recording, ``workers`` processes; unreadable recordings give ``{error}``."""
    hold = [str(p) for p in holdout or []]
    out = []
    with ProcessPoolExecutor(max(1, workers)) as pool:
        futs = {pool.submit(_one, str(p), str(params_path) if params_path else None, hold): p for p in paths}
        for i, f in enumerate(as_completed(futs), 1):
            r = f.result()
            progress(f"[diagnose] {i}/{len(paths)} {r['recording']}: {r.get('verdict', r.get('error'))}")
            out.append(r)
    order = {str(p): i for i, p in enumerate(paths)}
    return sorted(out, key=lambda r: order[r["recording"]])
