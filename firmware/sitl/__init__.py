"""A PX4-compatible MAVLink autopilot emulator: a point-mass multicopter that MAVSDK can fly.

PX4 cannot be built here, so this stands in for it in tests and demos. `vehicle` is the pure
physics and mode machine (time is passed in), `commands` maps MAVLink commands onto it,
`streams` turns its state into PX4's telemetry, `mavlink_io` is the UDP link, `app` is the
real-time loop and `cli` the `covey sitl` command line. `onboard` flies goto targets with the
C policy (`firmware.cpolicy`), avoiding the ADSB_VEHICLE traffic the relay forwards.
"""

from firmware.sitl.config import SitlConfig

__all__ = ["SitlConfig"]
