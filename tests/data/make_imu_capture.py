"""Regenerate ``imu_capture.bin``: bytes read from the simulated VectorNav IMU's pty.

Run: ``.venv/bin/python tests/data/make_imu_capture.py``. The stream holds register replies,
$VNIMU and $VNYMR sentences and injected faults, in this order (the CLI test relies on it):

1. replies to ``$VNWRG,06,19`` and ``$VNWRG,07,50`` (sent with the ``*XX`` checksum bypass);
2. 12 $VNIMU sentences k = 0..11 with accel = (0.1 k, -0.2 k, 9.807) m/s^2 and
   gyro = (0.003 k, -0.001 k, 0.5) rad/s; 7 garbage bytes after k = 3; k = 5 has a bad
   checksum; k = 8 is truncated;
3. the reply to ``$VNWRG,06,14`` (switch to $VNYMR), 3 $VNYMR sentences with
   accel = (1, 2, 3 + j), gyro = (0.1, 0.2, 0.3 j), ypr = (10 j, 1, -2) deg, j = 0..2;
4. ``$VNERR,07`` answering ``$VNWRG,07,3`` (3 Hz is not an output rate);
5. one more $VNYMR, truncated at the end of the file.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import serial

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from sim.imu import SimulatedIMU  # noqa: E402

OUT = Path(__file__).with_name("imu_capture.bin")


def main() -> None:
    capture = bytearray()
    with SimulatedIMU(output="VNOFF", rate_hz=40) as sim:
        port = serial.Serial(sim.port, 115200, timeout=0)

        def command(cmd: bytes, reply: bytes) -> None:
            """Send ``cmd`` and read until ``reply`` (the start of the answer) arrives."""
            time.sleep(0.02)
            capture.extend(port.read(65536))
            start = len(capture)
            port.write(cmd)
            deadline = time.monotonic() + 2.0
            while reply not in capture[start:]:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"simulator did not answer {cmd!r}")
                time.sleep(0.002)
                capture.extend(port.read(4096))
            while not capture.endswith(b"\n"):
                capture.extend(port.read(4096))

        command(b"$VNWRG,06,19*XX\r\n", b"$VNWRG,06")
        command(b"$VNWRG,07,50*XX\r\n", b"$VNWRG,07")
        for k in range(12):
            corrupt = {5: "checksum", 8: "truncate"}.get(k)
            sim.publish([0.1 * k, -0.2 * k, 9.807], [0.003 * k, -0.001 * k, 0.5], corrupt=corrupt)
            if k == 3:
                sim.write_garbage(7, seed=3)
        command(b"$VNWRG,06,14*XX\r\n", b"$VNWRG,06")
        for j in range(3):
            sim.publish([1.0, 2.0, 3.0 + j], [0.1, 0.2, 0.3 * j], ypr=(10.0 * j, 1.0, -2.0))
        command(b"$VNWRG,07,3*XX\r\n", b"$VNERR")
        sim.publish([0.0, 0.0, 9.8], [0.0, 0.0, 0.0], corrupt="truncate")
        time.sleep(0.05)
        capture.extend(port.read(4096))
        port.close()
    OUT.write_bytes(bytes(capture))
    print(f"wrote {OUT} ({len(capture)} bytes)")


if __name__ == "__main__":
    main()
