"""The loop's recording: what ``LoopRunner`` (``otbot_hw.runtime.loop``) writes per sample and per
event, and where it goes.

* ``LoopRecording`` — the recording part of the runner (mixed into ``LoopRunner``): the topics
  chosen at the first sample (joints, events, IMU, truth, estimate, reference, payload), the
  metadata, the writer (``RecordingWriter`` to ``path``, or the ``recorder``'s, e.g. a
  ``SessionRecording``), ``start_recording``/``stop_recording`` between cycles, ``event()``, the
  samples kept in memory (``keep_samples``) and the ``Recording`` built from them.
* ``record_after_write``: in a real-time loop each sample is written once the cycle's command is
  out (the JSON and MCAP encoding and the file I/O no longer sit between the read and the write;
  the file order is unchanged, a pending sample goes out before any event, flush or close).
* ``BackgroundWriter`` — ``record_in_background``: a writer fed from the loop thread and written by
  a thread of its own (measured in docs/performance.md: it costs the process more CPU than it
  takes off the loop).
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Any

import numpy as np

from otbot_hw.recording import (TOPIC_COMMAND, TOPIC_ESTIMATE, TOPIC_EVENTS, TOPIC_IMU, TOPIC_JOINTS,
                                TOPIC_PAYLOAD, TOPIC_REFERENCE, TOPIC_TRUTH, Recording, RecordingWriter,
                                source_metadata)
from otbot_hw.robot import Snapshot
from otbot_hw.runtime.controllers import Reference
from otbot_hw.runtime.feedback import StateEstimate

_NAN3 = np.full(3, np.nan)
_ZERO2 = np.zeros(2)
_NO_REFERENCE = Reference(_NAN3, _NAN3, _NAN3)


class _Columns:
    """Per-sample rows kept in memory (to build the ``Recording`` and the run's summaries)."""

    NAMES = ("t", "torque", "requested", "u_traj", "u_corr", "pos", "vel", "acc", "gyro", "truth", "force", "pose",
             "twist", "std", "bias", "ref_p", "ref_pd", "ref_pdd")

    def __init__(self):
        for n in self.NAMES:
            setattr(self, n, [])



class BackgroundWriter:
    """A recording writer (``RecordingWriter``, ``SessionRecording``) fed from the loop thread and
    written by a thread of its own: ``write_sample``/``write_event`` only queue (in order, O(1));
    the JSON encoding, MCAP framing, file writes and flushes run in the ``recording-writer`` thread,
    which drains the queue when ``wake()`` is called — the loop calls it once its cycle has written
    its command, so the writer holds the interpreter while the loop waits for the next period, not
    in the middle of its compute — at the latest every ``interval`` s, and at once when
    ``flush()``/``close()`` ask.
    ``flush()`` and ``close()`` return once everything queued before them is written (and flushed);
    more than ``max_queue`` waiting samples (a stalled disk) make ``write_sample`` wait for the
    writer, as writing in the loop did. An exception the writer raises is re-raised by the next call
    from the loop. Other attributes (``path``, ``error``, ``status()``, ...) are the writer's."""

    def __init__(self, writer, interval: float = 0.1, max_queue: int = 10000):
        self.writer = writer
        self.interval = float(interval)
        self.max_queue = int(max_queue)
        self._q: deque = deque()
        self._cv = threading.Condition()
        self._go = threading.Event()
        self._done = 0  # items written so far
        self._queued = 0  # items queued so far
        self._failure: BaseException | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="recording-writer", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Let the writer write what is queued (the loop's cycle is done)."""
        self._go.set()

    def __getattr__(self, name):
        return getattr(self.__dict__["writer"], name)

    def write_sample(self, messages: dict) -> None:
        self._check()
        self._q.append((0, messages))
        self._queued += 1
        if len(self._q) > self.max_queue:
            self._wait(self._queued - self.max_queue // 2)

    def write_event(self, t: float, kind: str, text: str, **extra) -> None:
        self._check()
        self._q.append((1, (t, kind, text, extra)))
        self._queued += 1

    def flush(self) -> None:
        """Everything queued so far written and flushed to the file (waits for the writer)."""
        self._check()
        self._q.append((2, None))
        self._queued += 1
        self._wait(self._queued)
        self._check()

    def close(self) -> None:
        """Write what is queued, close the writer and end the thread."""
        self._q.append((3, None))
        self._queued += 1
        self._closing = True
        self._go.set()
        self._thread.join()
        self._check()

    def _check(self) -> None:
        if self._failure is not None:
            exc, self._failure = self._failure, None
            raise exc

    def _wait(self, n: int) -> None:
        self._go.set()
        with self._cv:
            while self._done < n and self._thread.is_alive():
                self._cv.wait(0.1)

    def _run(self) -> None:
        w, q = self.writer, self._q
        while True:
            if not self._closing:
                self._go.wait(self.interval)
                self._go.clear()
            while q:
                what, item = q.popleft()
                try:
                    if what == 0:
                        w.write_sample(item)
                    elif what == 1:
                        t, kind, text, extra = item
                        w.write_event(t, kind, text, **extra)
                    elif what == 2:
                        w.flush()
                    else:
                        w.close()
                except BaseException as exc:  # noqa: BLE001 - handed to the loop thread
                    if self._failure is None:
                        self._failure = exc
                self._done += 1
                if what >= 2:
                    with self._cv:
                        self._cv.notify_all()
                    if what == 3:
                        return
            if self._done >= self._queued - self.max_queue // 2:
                with self._cv:
                    self._cv.notify_all()


class LoopRecording:
    """The recording part of ``LoopRunner``. Expects on the runner: ``robot``, ``period``,
    ``realtime``, ``feedback``, ``metadata``, ``path``, ``recorder``, ``keep_samples``, ``payload``,
    ``_held``, ``_u_held``, ``_has_imu``, ``_has_truth``, ``_truth_force``, ``_last_est``."""

    def _init_recording(self, path, recorder, record_reference, record_in_background,
                        record_after_write) -> None:
        self.path = path
        self.recorder = recorder
        self.record_reference = record_reference
        self.record_in_background = bool(record_in_background)
        # a sample written after the cycle's command (default: a real-time loop with a recorder)
        self.record_after_write = (recorder is not None and self.realtime) if record_after_write is None \
            else bool(record_after_write)
        self._pending_sample: dict | None = None
        self._deferred_events: list = []  # events said before this cycle's sample, written after it
        self.writer: RecordingWriter | None = None
        self.events: list[dict] = [] if self.keep_samples else deque(maxlen=1000)  # a daemon: the recent ones
        self._cols = _Columns()
        self._topics: set = set()
        self._topic_list: list = []

    def _open_writer(self, est, ref) -> None:
        topics = [TOPIC_JOINTS, TOPIC_EVENTS]
        if self._has_imu:
            topics.append(TOPIC_IMU)
        if self._has_truth:
            topics.append(TOPIC_TRUTH)
        if est is not None:
            topics.append(TOPIC_ESTIMATE)
        if self.record_reference or (self.record_reference is None and ref is not None):
            topics.append(TOPIC_REFERENCE)
        if self.payload is not None:
            topics.append(TOPIC_PAYLOAD)
        self._topics = set(topics)
        self._topic_list = topics
        meta = {**source_metadata(program="loop"), "sample_period": self.period, "realtime": self.realtime,
                **self.metadata}
        if self._has_imu and self.robot.imu_rate:
            meta.setdefault("imu_rate", float(self.robot.imu_rate))
        if self.feedback is not None:
            meta.setdefault("feedback", self.feedback.name)
        self.metadata = meta
        if self.path is not None:
            self.writer = RecordingWriter(self.path, meta, topics=topics)
        elif self.recorder is not None:
            self.writer = self._background(self.recorder(meta, topics))
        if self.writer is not None:
            for ev in self.events:
                self.writer.write_event(ev["t"], ev["kind"], ev["text"])

    def _background(self, writer):
        """The recorder's writer, written from its own thread when ``record_in_background``."""
        if writer is None or not self.record_in_background:
            return writer
        return BackgroundWriter(writer)

    @property
    def recording(self):
        """The writer samples go to (None: not recording)."""
        return self.writer

    def start_recording(self):
        """Between cycles: open a new recording with ``recorder`` (the same topics and metadata);
        returns the writer. Before the first sample the recording opens with it anyway."""
        if self.recorder is None:
            raise RuntimeError("this loop has no recorder")
        if self.writer is not None:
            raise RuntimeError("already recording")
        if not self._topics:
            return None
        self.writer = self._background(self.recorder(self.metadata, self._topic_list))
        return self.writer

    def stop_recording(self):
        """Between cycles: close the current recording (complete, with its summary); returns it."""
        self._write_pending()
        w, self.writer = self.writer, None
        if w is not None:
            w.close()
        return w

    def _record(self, s: Snapshot, est: StateEstimate | None, ref) -> None:
        if not self._topics:
            self._open_writer(est, ref)
        held = self._held
        acc = s.imu_accel if s.imu_accel is not None else _NAN3
        gyro = s.imu_gyro if s.imu_gyro is not None else _NAN3
        truth = self.robot.truth() if self._has_truth else None
        force = (self._truth_force() if self._truth_force is not None else _ZERO2) if self._has_truth else None
        e = est if est is not None else self._last_est
        r = ref if ref is not None else _NO_REFERENCE  # e.g. open loop before a tracking controller
        if self.keep_samples:
            c = self._cols
            c.t.append(s.t)
            c.torque.append(self._u_held)
            c.requested.append(held.u if held is not None else self._u_held)
            c.u_traj.append(held.u_traj if held is not None and held.u_traj is not None else _NAN3)
            c.u_corr.append(held.u_corr if held is not None and held.u_corr is not None else _NAN3)
            c.pos.append(s.joint_pos)
            c.vel.append(s.joint_vel)
            c.acc.append(acc)
            c.gyro.append(gyro)
            if self._has_truth:
                c.truth.append(truth)
                c.force.append(force)
            if TOPIC_ESTIMATE in self._topics:
                c.pose.append(e.pose)
                c.twist.append(e.twist)
                c.std.append(e.std)
                c.bias.append(e.gyro_bias)
            if TOPIC_REFERENCE in self._topics:
                c.ref_p.append(r.p)
                c.ref_pd.append(r.pd)
                c.ref_pdd.append(r.pdd)
        if self.writer is None:
            return
        t = s.t
        msg: dict[str, Any] = {TOPIC_COMMAND: {"t": t, "torque": self._u_held.tolist()},
                               TOPIC_JOINTS: {"t": t, "position": s.joint_pos.tolist(),
                                              "velocity": s.joint_vel.tolist()}}
        if self._has_imu:
            msg[TOPIC_IMU] = {"t": t, "accel": acc.tolist(), "gyro": gyro.tolist()}
        if truth is not None:
            msg[TOPIC_TRUTH] = {"t": t, "q": truth[:6].tolist(), "qd": truth[6:].tolist(), "force": force.tolist()}
        if TOPIC_ESTIMATE in self._topics:
            msg[TOPIC_ESTIMATE] = {"t": t, "pose": e.pose.tolist(), "twist": e.twist.tolist(),
                                   "std": e.std.tolist(), "gyro_bias": float(e.gyro_bias)}
        if TOPIC_REFERENCE in self._topics:
            msg[TOPIC_REFERENCE] = {"t": t, "p": r.p.tolist(), "pd": r.pd.tolist(), "pdd": r.pdd.tolist()}
        if TOPIC_PAYLOAD in self._topics:
            msg[TOPIC_PAYLOAD] = self.payload.message(t)
        if self.record_after_write:
            self._pending_sample = msg
        else:
            self.writer.write_sample(msg)

    def event(self, t: float, kind: str, text: str, defer: bool = False) -> None:
        """Record a sparse ``/otbot/events`` message (mode, fault, saturation, note). ``defer``: in a
        loop that writes its sample after the command (``record_after_write``), write it to the file
        after this cycle's sample instead of now, between the read and the write (the overrun event
        at the start of a streak: its encoding and the event's flush left the cycle's timed work);
        any event said before that goes out after it, in order."""
        self.events.append({"t": float(t), "kind": kind, "text": text})
        if self.writer is not None:
            if defer and self.record_after_write:
                self._deferred_events.append((t, kind, text))
                return
            if self._pending_sample is not None or self._deferred_events:  # what happened before, first
                self._write_pending()
            self.writer.write_event(t, kind, text)

    def _on_saturation(self, ep) -> None:
        self.event(ep.t_start, "saturation", f"{ep.motor} clamped to {ep.limit:g} N m (requested {ep.peak_request:.2f} N m)")
        if self._user_saturation is not None:
            self._user_saturation(ep)

    def _write_pending(self) -> None:
        msg, self._pending_sample = self._pending_sample, None
        if msg is not None and self.writer is not None:
            self.writer.write_sample(msg)
        if self._deferred_events:
            deferred, self._deferred_events = self._deferred_events, []
            if self.writer is not None:
                for t, kind, text in deferred:
                    self.writer.write_event(t, kind, text)

    def close(self) -> None:
        if self.writer is not None:
            self._write_pending()
            self.writer.close()
            self.writer = None

    def _recording_result(self) -> Recording:
        """The samples kept in memory as a ``Recording`` (empty without ``keep_samples``)."""
        c = self._cols
        n = len(c.t)

        def arr(rows, w):
            return np.array(rows, dtype=float).reshape(n, w)

        rec = Recording(t=np.array(c.t, dtype=float), torque=arr(c.torque, 3), joint_pos=arr(c.pos, 3),
                        joint_vel=arr(c.vel, 3), metadata=dict(self.metadata), events=list(self.events))
        if self._has_imu:
            rec.imu_accel, rec.imu_gyro = arr(c.acc, 3), arr(c.gyro, 3)
        if c.truth:
            x = arr(c.truth, 12)
            rec.truth_q, rec.truth_qd = x[:, :6].copy(), x[:, 6:].copy()
            rec.truth_force = arr(c.force, 2)
        if c.pose:
            rec.estimate_pose, rec.estimate_twist = arr(c.pose, 3), arr(c.twist, 3)
            rec.estimate_std, rec.estimate_gyro_bias = arr(c.std, 6), np.array(c.bias, dtype=float)
        if c.ref_p:
            rec.reference_p, rec.reference_pd, rec.reference_pdd = arr(c.ref_p, 3), arr(c.ref_pd, 3), arr(c.ref_pdd, 3)
        return rec
