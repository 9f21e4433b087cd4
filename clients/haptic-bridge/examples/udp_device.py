#!/usr/bin/env python3
"""A tiny stand-in for a vendor driver speaking haptic-bridge's UDP device protocol.

It sends a probe's pose every millisecond (pressing 3 mm into the skin at (1 cm, 1 cm)
and back) and prints the force the bridge sends back. Replace the trajectory with your
device SDK's pose (OpenHaptics hdGetDoublev, Force Dimension dhdGetPosition, …) and
render the received force with its force call. Protocol: docs/haptic-bridge.md.

    haptic-bridge --session ID --token T --tool 1 --device udp:127.0.0.1:7301
    python3 udp_device.py 127.0.0.1:7301
"""

import math
import socket
import struct
import sys
import time

# 80 bytes: CSD1, sequence, device ns, position m, quaternion wxyz, buttons (bit 0: cut or
# close the forceps; bit 1: the squeeze that follows is an analog gripper's), squeeze 0–1.
POSE = struct.Struct("<4sIQ3d4dIf")
# 64 bytes: CSF1, sequence, force N, torque N·m, flags, the force to render on an analog
# gripper against its squeeze N (forceps: how hard the jaws are pushed apart).
FORCE = struct.Struct("<4sI3d3dIf")


def main():
    host, port = (sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:7301").rsplit(":", 1)
    bridge = (host, int(port))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    start = time.monotonic()
    sequence = 0
    while time.monotonic() - start < 6.0:
        t = time.monotonic() - start
        z = 0.005 - 0.008 * min(t / 2.0, 1.0) if t < 4.0 else 0.005
        sequence += 1
        sock.sendto(POSE.pack(b"CSD1", sequence, time.monotonic_ns(), 0.01, 0.01, z, 1.0, 0.0, 0.0, 0.0, 0, 0.0), bridge)
        try:
            while True:
                data, _ = sock.recvfrom(128)
                magic, seq, fx, fy, fz, _tx, _ty, _tz, flags, _gripper_n = FORCE.unpack(data)
                if magic == b"CSF1" and seq % 250 == 0:
                    print(f"t={t:5.2f} s  z={z * 1000:5.2f} mm  force=({fx:+.3f}, {fy:+.3f}, {fz:+.3f}) N  link {'ok' if flags & 1 else 'stale'}")
        except BlockingIOError:
            pass
        time.sleep(max(0.0, start + sequence * 0.001 - time.monotonic()))


if __name__ == "__main__":
    main()
