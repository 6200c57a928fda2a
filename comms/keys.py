"""Every Zenoh key expression covey uses, and nothing else builds them.

    covey/<fleet>/v/<id>/state    pub/sub, latest-wins VehicleState
    covey/<fleet>/v/<id>/cmd      queryable: Command -> CommandAck
    covey/<fleet>/v/<id>/ack      pub/sub: a copy of every CommandAck the vehicle sent (recorders)
    covey/<fleet>/v/<id>/alive    liveliness token of a vehicle's agent
    covey/<fleet>/v/<id>/event    pub/sub Event
    covey/<fleet>/v/<id>/trace    pub/sub GuidanceTrace (agents with --trace-guidance; recorders)
    covey/<fleet>/gcs/<id>/alive  liveliness token of a ground station
    covey/<fleet>/roster          pub/sub and queryable: the authority-signed Roster (keyed mode)

Ground-station tokens carry the station id so that two stations can come and go independently
(a shared key would make one station's leave look like all of them leaving).
"""

from __future__ import annotations

import re

from comms.schema import MAX_VEHICLE_ID

ROOT = "covey"
_FLEET_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
_VEHICLE_KEY_RE = re.compile(
    r"^covey/([A-Za-z0-9_-]{1,32})/v/([0-9]{1,5})/(state|cmd|ack|alive|event|trace)$"
)
_GCS_KEY_RE = re.compile(r"^covey/([A-Za-z0-9_-]{1,32})/gcs/([0-9]{1,5})/alive$")


def check_fleet(fleet: str) -> str:
    """Return `fleet` if it is a valid fleet name, else raise ValueError saying why."""
    if not isinstance(fleet, str) or not _FLEET_RE.match(fleet):
        raise ValueError(f"fleet name {fleet!r} must be 1-32 characters of A-Z a-z 0-9 _ -")
    return fleet


def check_vehicle_id(vehicle_id: int) -> int:
    if (
        not isinstance(vehicle_id, int)
        or isinstance(vehicle_id, bool)
        or not 1 <= vehicle_id <= MAX_VEHICLE_ID
    ):
        raise ValueError(f"vehicle id {vehicle_id!r} must be an integer in 1..{MAX_VEHICLE_ID}")
    return vehicle_id


def _vehicle(fleet: str, vehicle_id: int | str, leaf: str) -> str:
    vid = "*" if vehicle_id == "*" else str(check_vehicle_id(vehicle_id))  # type: ignore[arg-type]
    return f"{ROOT}/{check_fleet(fleet)}/v/{vid}/{leaf}"


def state(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "state")


def all_states(fleet: str) -> str:
    return _vehicle(fleet, "*", "state")


def cmd(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "cmd")


def all_cmds(fleet: str) -> str:
    return _vehicle(fleet, "*", "cmd")


def ack(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "ack")


def all_acks(fleet: str) -> str:
    return _vehicle(fleet, "*", "ack")


def alive(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "alive")


def all_alive(fleet: str) -> str:
    return _vehicle(fleet, "*", "alive")


def event(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "event")


def all_events(fleet: str) -> str:
    return _vehicle(fleet, "*", "event")


def trace(fleet: str, vehicle_id: int) -> str:
    """Where a vehicle's guidance traces go: off the event key, so that stations and agents
    that follow events do not receive (and, keyed, verify) ten traces a second per vehicle."""
    return _vehicle(fleet, vehicle_id, "trace")


def gcs_alive(fleet: str, gcs_id: int) -> str:
    return f"{ROOT}/{check_fleet(fleet)}/gcs/{check_vehicle_id(gcs_id)}/alive"


def all_gcs_alive(fleet: str) -> str:
    return f"{ROOT}/{check_fleet(fleet)}/gcs/*/alive"


def roster(fleet: str) -> str:
    """Where a new fleet roster is pushed, and where every keyed member answers with its own."""
    return f"{ROOT}/{check_fleet(fleet)}/roster"


def everything(fleet: str) -> str:
    """Every key of one fleet (for the recorder)."""
    return f"{ROOT}/{check_fleet(fleet)}/**"


def parse_vehicle_key(key: str) -> tuple[str, int, str] | None:
    """(fleet, vehicle_id, leaf) of a vehicle key, or None if `key` is not one."""
    m = _VEHICLE_KEY_RE.match(str(key))
    if not m:
        return None
    vid = int(m.group(2))
    if not 1 <= vid <= MAX_VEHICLE_ID:
        return None
    return m.group(1), vid, m.group(3)


def parse_gcs_key(key: str) -> tuple[str, int] | None:
    m = _GCS_KEY_RE.match(str(key))
    if not m:
        return None
    return m.group(1), int(m.group(2))
