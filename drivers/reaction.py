"""Fault latching, the fault reaction and the stop paths of ``CanopenRobot`` (``drivers.robot``),
and the multi-SYNC power sequences (enable, disable, quick stop, fault reset).

Fault reaction (here, so it holds under any loop): a fault stages a quick stop with zero torque for
every drive and sends it at once; the SYNC cycle is then kept alive, for at most
``bus.reaction_timeout`` periods, until every drive still on the bus confirms QUICK STOP ACTIVE (or
a state without torque) in its own statusword; then the drives are disabled; a drive that does not
confirm gets NMT STOP, which a CiA 402 drive answers with its abort connection option (0x6007). A
fault found by ``read()`` is reacted to before ``read()`` returns; one found by a background thread
(EMCY, heartbeat) by a safety thread unless a ``read()`` is under way, which then does it. The
sequences' SYNCs come at the ticks of the runtime's clock (``self.clock``, ``otbot_hw.clock``): one
per period on a paced bus, back to back in lockstep; the driver never sleeps to pace.
"""
from __future__ import annotations

from drivers.cia402 import STOPPED_STATES
from drivers.device import NMT_STOP
from drivers.faults import DriverError
from otbot_hw.robot import Fault, RobotError, RobotFault

#: Fault kinds after which a node cannot confirm anything over PDOs.
OFF_BUS_KINDS = ("heartbeat", "stale", "nmt", "bus")


class FaultReaction:
    """Faults, the reaction and the power sequences: a part of ``CanopenRobot`` (state and locks are
    the robot's)."""

    MAX_ENABLE_CYCLES = 12

    def _bus_time(self, wall: float | None = None) -> float:
        """Bus time (s): cycle * period at the last SYNC, plus the wall time elapsed since it; on a
        clock that keeps no real time (lockstep) at most one period, since the next SYNC has not
        been sent (a loaded machine's delay between SYNCs is not bus time)."""
        if wall is None:
            return self._sync_t
        since = max(0.0, wall - self._sync_wall)
        if not self.clock.realtime:
            since = min(since, 0.999 * self.period)
        return self._sync_t + since

    def _add_fault(self, f: Fault, at_sync: bool = False) -> None:
        """Latch ``f``; start the fault reaction: quick stop with zero torque staged and sent to every
        drive at once (applied at the next SYNC), the rest of the reaction at the next cycle."""
        with self._lock:
            if any(g.device == f.device and g.kind == f.kind and g.code == f.code for g in self._faults):
                return
            self._faults.append(f)
            self._fault_t[f] = self._sync_t if at_sync else self._bus_time(f.time)
            self._fault_sync[f] = self._sync_index + (self._fault_t[f] - self._sync_t) / self.period
            if self._open and self._armed:
                self._reaction_pending = True
                for d in self.drives:
                    d.stage_quick_stop()
                    try:
                        d.transmit()
                    except Exception:  # noqa: BLE001 - the reaction retries and reports
                        pass
        if self._reaction_pending:
            self._wake.set()

    @property
    def faults(self) -> tuple[Fault, ...]:
        with self._lock:
            return tuple(self._faults)

    def fault_times(self) -> dict[Fault, float]:
        """Bus time (s since enabling, see ``_bus_time``) at which each active fault was detected."""
        with self._lock:
            return {f: self._fault_t[f] for f in self._faults}

    def fault_syncs(self) -> dict[Fault, float]:
        """When each active fault was detected, as the index of the SYNC since ``open()`` (a fault
        found between SYNCs: the last index plus the elapsed wall time in periods). A simulated
        plant counts the same SYNCs from the master's boot, so this is the clock both sides share."""
        with self._lock:
            return {f: self._fault_sync[f] for f in self._faults}

    def _safety_loop(self) -> None:
        while True:
            self._wake.wait()
            self._wake.clear()
            if not self._open:
                return
            with self._cycle_lock:
                if self._reaction_pending and self._armed and self._open:
                    try:
                        self._stop_drives("fault")
                    except Exception as exc:  # noqa: BLE001 - never let the thread die silently
                        self.problems.append(f"fault reaction failed: {type(exc).__name__}: {exc}")

    def _off_bus(self) -> set[int]:
        """Nodes that cannot confirm anything over PDOs (all of them once the bus itself failed)."""
        faults = self.faults
        if any(f.kind == "bus" for f in faults):
            return {d.node_id for d in self.devices}
        return {f.node for f in faults if f.kind in OFF_BUS_KINDS}

    def enable(self) -> None:
        faults = self.faults
        if faults:
            raise RobotFault("cannot enable while faulted: " + "; ".join(map(str, faults)), faults)
        with self._cycle_lock:
            self._armed = True
            try:
                for _ in range(self.MAX_ENABLE_CYCLES):
                    with self._lock:
                        done = [d.step_towards_enabled() for d in self.drives]
                        if all(done):
                            break
                        failed = self._send_rpdos(self.drives)
                    if failed:
                        self._add_fault(Fault("bus", None, "bus", "; ".join(failed)))
                    self._await_tick()
                    self.read()
                    if self.faults:
                        raise RobotFault("fault while enabling: " + "; ".join(map(str, self.faults)), self.faults)
                else:
                    states = ", ".join(f"{d.name}: {d.state}" for d in self.drives)
                    raise DriverError(f"drives did not reach OPERATION ENABLED in {self.MAX_ENABLE_CYCLES} cycles "
                                      f"({states})")
            except RobotError:
                if self._armed:
                    self._stop_drives("enable failed")  # the drives that did enable lose power again
                raise
            self.enabled = True
            self._cycle = 0

    def _stop_drives(self, reason: str, quick_stop: bool = True, disable: bool = True) -> dict:
        """Quick stop (SYNC kept alive until every drive still on the bus confirms a state without
        torque in its statusword, at most ``bus.reaction_timeout`` periods), NMT STOP for those that
        do not confirm, then disable. Call with the cycle lock held. Returns the reaction record."""
        with self._lock:
            self._reaction_pending = False
            self.enabled = False
        n_max = self.config.bus.reaction_timeout
        rec = {"reason": reason, "t": self._sync_t, "cycles": 0, "confirmed": [], "escalated": [],
               "not_sent": []}
        confirmed: set[int] = set()
        if quick_stop:
            for _ in range(n_max):
                with self._lock:
                    for d in self.drives:
                        d.stage_quick_stop()
                    rec["not_sent"] += self._send_rpdos(self.drives)
                arrived = self._sync_cycle(spaced=True)
                rec["cycles"] += 1
                off = self._off_bus()
                for d in self.drives:
                    if (d.node_id, d.status_tpdo) in arrived and d.state in STOPPED_STATES:
                        confirmed.add(d.node_id)
                if all(d.node_id in confirmed for d in self.drives if d.node_id not in off):
                    break
        for d in self.drives:
            if quick_stop and d.node_id not in confirmed:
                why = ("off the bus" if d.node_id in self._off_bus()
                       else f"no quick stop confirmed within {n_max} periods")
                try:
                    if d.node_id not in self._off_bus():  # our own NMT STOP: expected, no second reaction
                        self.heartbeats.expect_node(d.node_id, "STOPPED")
                        self._nmt_stopped.add(d.node_id)
                    d.nmt_command(NMT_STOP)
                    rec["escalated"].append(d.name)
                    msg = f"{d.name} (node {d.node_id}): {why}: NMT STOP sent (the drive applies 0x6007)"
                except Exception as exc:  # noqa: BLE001
                    msg = f"{d.name} (node {d.node_id}): {why}: NMT STOP not sent: {exc}"
                self.problems.append(msg)
                if d.node_id not in self._off_bus():
                    self._add_fault(d.fault("statusword", f"{why} ({reason})"))
        if disable:
            reachable = [d for d in self.drives if d.node_id not in self._off_bus() | self._nmt_stopped]
            if reachable:
                with self._lock:
                    for d in self.drives:
                        d.stage_disable()
                    rec["not_sent"] += self._send_rpdos(reachable)
                for _ in range(n_max):
                    arrived = self._sync_cycle(spaced=True)
                    rec["cycles"] += 1
                    if all((d.node_id, d.status_tpdo) in arrived and d.state not in ("OPERATION ENABLED",
                                                                                  "QUICK STOP ACTIVE")
                           for d in reachable):
                        break
            self._armed = False
        with self._lock:
            self._reaction_pending = False
        rec["confirmed"] = [d.name for d in self.drives if d.node_id in confirmed]
        self.problems += [p for p in rec["not_sent"] if p not in self.problems]
        self.reactions.append(rec)
        return rec

    def disable(self) -> None:
        with self._cycle_lock:
            if self._open:
                self._stop_drives("disable", quick_stop=False)

    def quick_stop(self) -> None:
        """Quick stop every drive, confirmed by their statuswords (SYNC kept alive for at most
        ``bus.reaction_timeout`` periods; NMT STOP for a drive that does not confirm). After a fault
        the drives are disabled as well."""
        with self._cycle_lock:
            if self._open and self._armed:
                self._stop_drives("quick stop", disable=bool(self.faults))

    def fault_reset(self) -> None:
        with self._cycle_lock:
            for node in sorted(self._nmt_stopped):  # escalated nodes kept their setup: start their PDOs again
                dev = next(d for d in self.devices if d.node_id == node)
                try:
                    dev.start()
                except Exception as exc:  # noqa: BLE001 - reported; the heartbeat check says the rest
                    self.problems.append(f"{dev.name} (node {node}): NMT START not sent: {exc}")
            self._nmt_stopped.clear()
            for edge in (False, True):
                with self._lock:
                    for d in self.drives:
                        d.stage_fault_reset(edge)
                    self._send_rpdos(self.drives)
                self._sync_cycle(spaced=True)
            with self._lock:
                self._faults.clear()
                self._fault_t.clear()
                self._fault_sync.clear()
                self._misses.clear()
                self.problems.clear()
                for d in self.drives:
                    d.stage_disable()
            self.heartbeats.expect_state("OPERATIONAL")
            self.enabled = False
