"""Simulated CANopen slaves built on canopen's ``LocalNode``: ``node`` (``SimulatedNode``, what every slave
does: SDO server, NMT, heartbeat, PDO mapping, SYNC, EMCY), ``drive`` (``SimulatedDrive``, a CiA 402 torque
drive with its drive-side watchdogs) and ``encoder`` (``SimulatedEncoder``, a CiA 406 absolute encoder).

Each slave serves SDO requests over its EDS object dictionary (canopen's ``SdoServer``), boots
with an NMT boot-up message and produces heartbeats (``NmtSlave``), obeys NMT commands (reset
node / reset communication reboot it), maps PDOs as the master configures them over SDO, applies
synchronous RPDOs and transmits synchronous TPDOs when the plant calls ``latch()`` / ``send_tpdos()``
on every SYNC, and sends EMCY messages on faults. Joint quantities come from the plant, which
owns the physics; the slaves turn them into device units with their own conversions, written
from the CiA 402 / 406 definitions (not the driver's). A slave has only the objects its EDS
describes: whatever the dictionary lacks, the device lacks.

The drive's own protection (watchdogs, abort connection option) and its fault injection for tests
are described in ``drive``.
"""
