"""Many recordings diagnosed in parallel (a fleet's day of runs), each on its own.

``diagnose_each`` runs one diagnosis per recording on the identification's shared
executor (``otbot_hw.identification.executors.make_executor``): local worker
processes by default, a Dask distributed cluster when given a scheduler address. The
recordings are read and checked here and shipped to the workers with the parameters,
so a remote cluster needs no shared file system. The unit of work is
``diagnose_task(task)``; a recording that cannot be read or diagnosed gives
``{"recording", "error"}`` and the others go on.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from otbot_hw.identification.executors import Executor, LocalExecutor, make_executor
from otbot_hw.params import OtbotParams


def diagnose_task(task: dict[str, Any]) -> dict:
    """Diagnose ``task["data"]`` (one ``DiagnosisData``) against ``task["params"]`` with ``task["holdout"]``
    (list of ``DiagnosisData``); runs on a worker. ``task["threads"]`` (local worker processes only) sets
    the simulation threads of that process so the workers together fill the CPUs without oversubscribing."""
    from otbot_hw.diagnose.diagnosis import diagnose
    from otbot_hw.identification.model import set_prediction_threads

    if task.get("threads"):
        set_prediction_threads(task["threads"])
    try:
        r = diagnose([task["data"]], task["params"], task["holdout"], geometry=task.get("geometry"))
    except ValueError as exc:  # includes bad-input errors raised by the diagnosis
        r = {"error": f"{task['recording']}: {exc}"}
    r["recording"] = task["recording"]
    return r


def diagnose_each(paths: list[Path], params: OtbotParams, holdout: list[Path] | None = None,
                  executor: Executor | None = None, scheduler: str | None = None, workers: int | None = None,
                  progress=lambda msg: None, geometry=None) -> list[dict]:
    """One diagnosis per recording, in the order of ``paths``; unreadable recordings give ``{error}``.

    Runs on ``executor`` when given, else on ``make_executor(scheduler, workers)`` (closed afterwards).
    ``holdout`` recordings judge every diagnosis; an unreadable one raises ``RecordingError``.
    ``geometry``: caster and IMU positions (``geometry.EffectGeometry``) of the robot.
    """
    from otbot_hw.diagnose.data import load
    from otbot_hw.recording import RecordingError

    held = load(list(holdout or []))
    tasks, out = [], {}
    for p in paths:
        try:
            (data,) = load([p])
        except RecordingError as exc:
            out[str(p)] = {"recording": str(p), "error": str(exc)}
            continue
        tasks.append({"recording": str(p), "data": data, "params": params, "holdout": held, "geometry": geometry})
    own = executor is None
    ex = make_executor(scheduler, workers) if own else executor
    try:
        if isinstance(ex, LocalExecutor):
            for t in tasks:
                t["threads"] = max(1, (os.cpu_count() or 1) // ex.workers)
        progress(f"[diagnose] {len(tasks)} recording(s) on {ex.describe()}")
        results = ex.map(diagnose_task, tasks,
                         progress=lambda done, total: progress(f"[diagnose] {done}/{total} recordings diagnosed"))
    finally:
        if own:
            ex.close()
    for r in results:
        out[r["recording"]] = r
        progress(f"[diagnose] {r['recording']}: {r.get('verdict', r.get('error'))}")
    return [out[str(p)] for p in paths]
