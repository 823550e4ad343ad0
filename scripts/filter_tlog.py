"""Keep only the battery-relevant messages of a MAVLink telemetry log (``.tlog``), byte for byte.

A ``.tlog`` is a sequence of records: an 8-byte big-endian microsecond timestamp (the ground
station's receive time) followed by one MAVLink packet as received. This script copies the
records whose message type is in ``KEEP`` unchanged (timestamp and packet bytes), dropping the
rest, so a real flight's battery telemetry fits in a small test file. Used once to make
``examples/logs/real/arducopter_dronekit_flight_battery.tlog`` from dronekit-python's
``examples/flight_replay/flight.tlog`` (2.7 MB, Apache-2.0); see the MANIFEST there.

    python scripts/filter_tlog.py IN.tlog OUT.tlog
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

KEEP = frozenset(
    {"HEARTBEAT", "SYS_STATUS", "BATTERY_STATUS", "STATUSTEXT", "PARAM_VALUE", "AUTOPILOT_VERSION"}
)


def main(src: Path, dst: Path) -> int:
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(src))
    kept = total = 0
    with dst.open("wb") as out:
        while True:
            msg = conn.recv_match()
            if msg is None:
                break
            total += 1
            if msg.get_type() not in KEEP:
                continue
            stamp = round(msg._timestamp * 1e6)
            out.write(struct.pack(">Q", stamp) + bytes(msg.get_msgbuf()))
            kept += 1
    print(f"kept {kept} of {total} messages: {dst} ({dst.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2])))
