"""A PX4-compatible MAVLink autopilot emulator: a point-mass multicopter that MAVSDK can fly.

PX4 cannot be built here, so this stands in for it in tests and demos (see README.md).
`vehicle` is the pure physics and mode machine (time is passed in; settings in `params`, PX4's
mode numbers and MAV_RESULTs in `px4`), `commands` maps MAVLink commands, parameters, setpoints
and traffic onto it, `streams` turns its state into PX4's telemetry over the UDP link of
`comms.mavlink_udp`, `emulator` the real-time loop, `cli` the `covey sitl` command line and
`process` runs it as a child process. `onboard` flies goto targets with the C policy
(`firmware.cpolicy`), avoiding the ADSB_VEHICLE traffic (`traffic`) the relay forwards.
"""

from firmware.sitl.config import SitlConfig

__all__ = ["SitlConfig"]
