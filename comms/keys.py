"""Every Zenoh key expression covey uses, and nothing else builds them.

    covey/<fleet>/c/<cn>/<ce>/v/<id>/state
                                  pub/sub, latest-wins VehicleState, in the grid cell (cn, ce) of
                                  its position (see below)
    covey/<fleet>/v/<id>/cmd      queryable: Command -> CommandAck
    covey/<fleet>/v/<id>/alive    liveliness token of a vehicle's agent
    covey/<fleet>/msg/<id>/ack    pub/sub: a copy of every CommandAck the vehicle sent (below)
    covey/<fleet>/msg/<id>/event  pub/sub Event, and ActionOutcome (the autopilot's outcome of
                                  a command; the first byte tells them apart)
    covey/<fleet>/msg/<id>/trace  pub/sub GuidanceTrace (agents with --trace-guidance; recorders)
    covey/<fleet>/msg/<id>/feed   pub/sub FeedBatch: the latest states of the vehicles of one
                                  process, batched at a bounded rate (ground stations); <id> is
                                  the first vehicle that process published (comms/feed.py)
    covey/<fleet>/gcs/<id>/alive  liveliness token of a ground station
    covey/<fleet>/gcs/<id>/heartbeat
                                  pub/sub StationHeartbeat, signed by station <id> (keyed mode):
                                  what the station-lost failsafe trusts (trust/heartbeat.py)
    covey/<fleet>/gcs/<id>/traffic
    covey/<fleet>/msg/<id>/traffic
                                  pub/sub TrafficReport: vehicles that do not cooperate, as station
                                  <id> (an intruder, a hand-flown vehicle) or vehicle <id>'s
                                  ADS-B receiver sees them, signed by <id> (agent/traffic.py)
    covey/<fleet>/relay/<rid>/<k>/<cn>/<ce>
                                  pub/sub RelayBatch: the states router <rid> (its Zenoh id) heard
                                  in the cells within k of cell (cn, ce), once a relay period
                                  (comms/relay.py)
    covey/<fleet>/v/<id>/want/<rid>/<k>/<cn>/<ce>
                                  liveliness token: vehicle <id> wants that block from relay <rid>
    covey/<fleet>/roster          pub/sub and queryable: the authority-signed Roster (keyed mode)
    covey/<fleet>/plan            pub/sub and queryable: the signed fleet plan (fence, keep-out
                                  zones, rally points), followed like the roster (comms/plan_sync.py)

A state's key carries the coarse grid cell of the position it reports, so that a vehicle can
subscribe to the cells within its reach (comms/scope.py, docs/scaling.md) instead of the whole
fleet: `cell_states` is one cell of every vehicle, `all_states` every state of the fleet (the
station, recorders; its `**` also matches the unplaced `covey/<fleet>/v/<id>/state` that tools
may put, which scoped subscribers hear too). The key still ends in its leaf (`.../state`).
The cell comes *before* the vehicle id: a Zenoh router that gets a state from another router
matches its key against its whole resource tree for every message (the route is not cached for
keys it learnt nothing about), and that walk visits every sibling of each chunk. Under
`covey/<fleet>/v/` every vehicle of the fleet is a sibling; under `covey/<fleet>/c/<cn>/<ce>/v/`
only the few vehicles of one cell are, so routing one state costs a router about the same at any
fleet size (docs/scaling.md, "Routers"). For the same reason what a vehicle *sends* (acks,
events, traces, feeds) lives under `msg/<id>/`, and `v/<id>/` keeps what it *declares* once
(its command queryable and presence token, which every router knows, one per vehicle): a
message under `v/` would make each router that forwards it try every vehicle of the fleet.
Access control gives vehicle N `covey/<fleet>/v/N/**`, `covey/<fleet>/msg/N/**` and
`covey/<fleet>/c/*/*/v/N/state` (comms/zenoh_configs). Recordings made before these layouts
(`covey/<fleet>/v/<id>/c/<cn>/<ce>/state`, `covey/<fleet>/v/<id>/{ack,event,trace,feed}`)
still parse.
The cell must be the one of the state's own position (`cell_of`): the mesh refuses a state on
any other cell, so a vehicle cannot hide from its neighbours by publishing in a far cell.

A feed lives under its process's first vehicle so that a one-vehicle process (every keyed
agent) publishes only under its own keys, as the routers' access-control rules allow;
its entries may name any vehicle, and each is checked as a state is (signature, order).

Every ack goes two ways, and both are needed: the reply to the command's query reaches only
the querier (the station that sent it, whose `send_command` waits on it), and the copy on
`msg/<id>/ack` reaches everyone else: recorders, and every other station, whose command logs
show every station's commands with each vehicle's answer. The sending station hears its acks
both ways; only the copy feeds its command log, which keeps one answer per (vehicle, nonce).

Ground-station tokens carry the station id so that two stations can come and go independently
(a shared key would make one station's leave look like all of them leaving).
"""

from __future__ import annotations

import math
import re
import struct

from comms.schema import MAX_VEHICLE_ID, POSITION_LIMIT_M

ROOT = "covey"
_FLEET_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")
CELL_M = 30.0
"""Pitch of the state grid in metres, north and east. A fleet-wide wire constant: a publisher
and its receivers must agree on it (a state on another cell than its position's is refused)."""
MAX_CELL = math.ceil(POSITION_LIMIT_M / CELL_M)
"""Largest |cell index| a valid position can have."""
Cell = tuple[int, int]
"""(north index, east index) of a grid cell: floor(n / CELL_M), floor(e / CELL_M)."""
_VEHICLE_KEY_RE = re.compile(
    r"^covey/(?P<fleet>[A-Za-z0-9_-]{1,32})/(?P<ns>v|msg)/(?P<vid>[0-9]{1,5})"
    r"/(?P<leaf>state|cmd|ack|alive|event|trace)$"
)
_LEAVES = {
    "v": ("state", "cmd", "alive", "ack", "event", "trace"),
    "msg": ("ack", "event", "trace"),
}
"""Which leaves live where: under v/<id>/ the unplaced state, the command queryable and the
presence token (and, in recordings made before `msg/`, acks, events and traces)."""
_CELL_STATE_KEY_RE = re.compile(
    r"^covey/(?P<fleet>[A-Za-z0-9_-]{1,32})/c/(?P<cn>-?[0-9]{1,6})/(?P<ce>-?[0-9]{1,6})"
    r"/v/(?P<vid>[0-9]{1,5})/state$"
)
_LEGACY_CELL_STATE_KEY_RE = re.compile(
    r"^covey/(?P<fleet>[A-Za-z0-9_-]{1,32})/v/(?P<vid>[0-9]{1,5})"
    r"/c/(?P<cn>-?[0-9]{1,6})/(?P<ce>-?[0-9]{1,6})/state$"
)
"""The layout of recordings made before the cell came first: parsed, never published."""
_FEED_KEY_RE = re.compile(r"^covey/([A-Za-z0-9_-]{1,32})/(?:msg|v)/([0-9]{1,5})/feed$")
_F32 = struct.Struct("<2f")
_RELAY_ID_RE = re.compile(r"^[0-9a-f]{1,32}$")
_CELL_TAIL = r"(?P<k>[0-9])/(?P<cn>-?[0-9]{1,6})/(?P<ce>-?[0-9]{1,6})$"
_RELAY_BLOCK_KEY_RE = re.compile(
    r"^covey/(?P<fleet>[A-Za-z0-9_-]{1,32})/relay/(?P<rid>[0-9a-f]{1,32})/" + _CELL_TAIL
)
_RELAY_WANT_KEY_RE = re.compile(
    r"^covey/(?P<fleet>[A-Za-z0-9_-]{1,32})/v/(?P<vid>[0-9]{1,5})/want/(?P<rid>[0-9a-f]{1,32})/"
    + _CELL_TAIL
)
MAX_RELAY_REACH_CELLS = 3
"""A relay block spans at most the (2k + 1)^2 cells within k <= this of its anchor cell."""
_GCS_KEY_RE = re.compile(r"^covey/([A-Za-z0-9_-]{1,32})/gcs/([0-9]{1,5})/alive$")
_HEARTBEAT_KEY_RE = re.compile(r"^covey/([A-Za-z0-9_-]{1,32})/gcs/([0-9]{1,5})/heartbeat$")


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


def _vehicle(fleet: str, vehicle_id: int | str, leaf: str, ns: str = "v") -> str:
    """`covey/<fleet>/<ns>/<id or *>/<leaf>`: ns "v" for what a vehicle declares, "msg" for what
    it sends (module docstring)."""
    vid = "*" if vehicle_id == "*" else str(check_vehicle_id(vehicle_id))  # type: ignore[arg-type]
    return f"{ROOT}/{check_fleet(fleet)}/{ns}/{vid}/{leaf}"


def cell_of(pos_ned_m: tuple[float, ...]) -> Cell:
    """The grid cell of a position, computed on the float32 values the wire carries, so that
    the sender and every receiver get the same cell even on a cell border."""
    n, e = _F32.unpack(_F32.pack(pos_ned_m[0], pos_ned_m[1]))
    return math.floor(n / CELL_M), math.floor(e / CELL_M)


def check_cell(cell: tuple[int, ...]) -> Cell:
    if (
        not isinstance(cell, tuple)
        or len(cell) != 2
        or not all(isinstance(c, int) and -MAX_CELL <= c <= MAX_CELL for c in cell)
    ):
        raise ValueError(f"cell {cell!r} must be two integers within +-{MAX_CELL}")
    return (cell[0], cell[1])


def state(fleet: str, vehicle_id: int, cell: Cell | None = None) -> str:
    """The key of a state of `vehicle_id` in `cell`; without a cell, the unplaced key that only
    whole-fleet subscribers hear (tools, tests)."""
    if cell is None:
        return _vehicle(fleet, vehicle_id, "state")
    cn, ce = check_cell(cell)
    return f"{ROOT}/{check_fleet(fleet)}/c/{cn}/{ce}/v/{check_vehicle_id(vehicle_id)}/state"


def all_states(fleet: str) -> str:
    """Every state of the fleet, placed or not."""
    return f"{ROOT}/{check_fleet(fleet)}/**/v/*/state"


def unplaced_states(fleet: str) -> str:
    """States put without a cell (tools, tests): every scoped subscriber hears these too."""
    return _vehicle(fleet, "*", "state")


def vehicle_states(fleet: str, vehicle_id: int) -> str:
    """Every state of one vehicle, in whichever cell."""
    return f"{ROOT}/{check_fleet(fleet)}/**/v/{check_vehicle_id(vehicle_id)}/state"


def cell_states(fleet: str, cell: Cell) -> str:
    """The states of every vehicle in one grid cell."""
    cn, ce = check_cell(cell)
    return f"{ROOT}/{check_fleet(fleet)}/c/{cn}/{ce}/v/*/state"


def check_relay_id(relay_id: str) -> str:
    """A relay's id: its router's Zenoh id, lower-case hex."""
    if not isinstance(relay_id, str) or not _RELAY_ID_RE.match(relay_id):
        raise ValueError(f"relay id {relay_id!r} must be 1-32 lower-case hex digits")
    return relay_id


def check_reach_cells(reach_cells: int) -> int:
    if not isinstance(reach_cells, int) or not 1 <= reach_cells <= MAX_RELAY_REACH_CELLS:
        raise ValueError(f"reach {reach_cells!r} must be 1..{MAX_RELAY_REACH_CELLS} cells")
    return reach_cells


def relay_block(fleet: str, relay_id: str, reach_cells: int, anchor: Cell) -> str:
    """Where relay `relay_id` puts the states of the cells within `reach_cells` of `anchor`."""
    cn, ce = check_cell(anchor)
    k = check_reach_cells(reach_cells)
    return f"{ROOT}/{check_fleet(fleet)}/relay/{check_relay_id(relay_id)}/{k}/{cn}/{ce}"


def relay_want(fleet: str, vehicle_id: int, relay_id: str, reach_cells: int, anchor: Cell) -> str:
    """Vehicle `vehicle_id`'s token asking relay `relay_id` for that block (under its own v/<id>/,
    which access control lets it declare)."""
    cn, ce = check_cell(anchor)
    k = check_reach_cells(reach_cells)
    rid = check_relay_id(relay_id)
    return f"{_vehicle(fleet, vehicle_id, 'want')}/{rid}/{k}/{cn}/{ce}"


def all_relay_wants(relay_id: str) -> str:
    """Every vehicle's wants of relay `relay_id`, in every fleet (a router serves them all)."""
    return f"{ROOT}/*/v/*/want/{check_relay_id(relay_id)}/**"


def _relay_tail(m: re.Match) -> tuple[int, Cell] | None:
    k, cn, ce = int(m["k"]), int(m["cn"]), int(m["ce"])
    if not 1 <= k <= MAX_RELAY_REACH_CELLS or max(abs(cn), abs(ce)) > MAX_CELL:
        return None
    return k, (cn, ce)


def parse_relay_block(key: str) -> tuple[str, str, int, Cell] | None:
    """(fleet, relay id, reach in cells, anchor) of a relay block key, or None if not one."""
    m = _RELAY_BLOCK_KEY_RE.match(str(key))
    tail = None if m is None else _relay_tail(m)
    if m is None or tail is None:
        return None
    return m["fleet"], m["rid"], tail[0], tail[1]


def parse_relay_want(key: str) -> tuple[str, int, str, int, Cell] | None:
    """(fleet, vehicle id, relay id, reach in cells, anchor) of a want token, or None."""
    m = _RELAY_WANT_KEY_RE.match(str(key))
    tail = None if m is None else _relay_tail(m)
    if m is None or tail is None or not 1 <= int(m["vid"]) <= MAX_VEHICLE_ID:
        return None
    return m["fleet"], int(m["vid"]), m["rid"], tail[0], tail[1]


def block_cells(reach_cells: int, anchor: Cell) -> list[Cell]:
    """The cells of a relay block, row by row."""
    k = check_reach_cells(reach_cells)
    cn, ce = check_cell(anchor)
    return [
        (n, e)
        for n in range(cn - k, cn + k + 1)
        for e in range(ce - k, ce + k + 1)
        if max(abs(n), abs(e)) <= MAX_CELL
    ]


def block_of(cells: frozenset[Cell] | set[Cell]) -> tuple[int, Cell] | None:
    """(k, anchor) if `cells` are exactly a relay block's (a square of side 2k + 1 within the
    grid), else None."""
    if not cells:
        return None
    ns = [c[0] for c in cells]
    es = [c[1] for c in cells]
    side = max(ns) - min(ns) + 1
    if side != max(es) - min(es) + 1 or side % 2 == 0 or len(cells) != side * side:
        return None
    k = side // 2
    if not 1 <= k <= MAX_RELAY_REACH_CELLS:
        return None
    return k, (min(ns) + k, min(es) + k)


def cmd(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "cmd")


def all_cmds(fleet: str) -> str:
    return _vehicle(fleet, "*", "cmd")


def _msg(fleet: str, vehicle_id: int | str, leaf: str) -> str:
    """A key of a vehicle's messages (acks, events, traces, feeds): under `msg/`, not `v/`, whose
    every vehicle's queryable and token make a router's walk of it as long as the fleet."""
    return _vehicle(fleet, vehicle_id, leaf, ns="msg")


def ack(fleet: str, vehicle_id: int) -> str:
    return _msg(fleet, vehicle_id, "ack")


def all_acks(fleet: str) -> str:
    return _msg(fleet, "*", "ack")


def alive(fleet: str, vehicle_id: int) -> str:
    return _vehicle(fleet, vehicle_id, "alive")


def all_alive(fleet: str) -> str:
    return _vehicle(fleet, "*", "alive")


def event(fleet: str, vehicle_id: int) -> str:
    return _msg(fleet, vehicle_id, "event")


def all_events(fleet: str) -> str:
    return _msg(fleet, "*", "event")


def trace(fleet: str, vehicle_id: int) -> str:
    """Where a vehicle's guidance traces go: off the event key, so that stations and agents
    that follow events do not receive (and, keyed, verify) ten traces a second per vehicle."""
    return _msg(fleet, vehicle_id, "trace")


def feed(fleet: str, vehicle_id: int) -> str:
    """The feed of the process whose first published vehicle is `vehicle_id`."""
    return _msg(fleet, vehicle_id, "feed")


def all_feeds(fleet: str) -> str:
    """Every process's feed: the whole fleet at a bounded rate (ground stations)."""
    return _msg(fleet, "*", "feed")


def parse_feed_key(key: str) -> tuple[str, int] | None:
    """(fleet, vehicle id it lives under) of a feed key, or None if `key` is not one."""
    m = _FEED_KEY_RE.match(str(key))
    if not m or not 1 <= int(m.group(2)) <= MAX_VEHICLE_ID:
        return None
    return m.group(1), int(m.group(2))


def gcs_alive(fleet: str, gcs_id: int) -> str:
    return f"{ROOT}/{check_fleet(fleet)}/gcs/{check_vehicle_id(gcs_id)}/alive"


def all_gcs_alive(fleet: str) -> str:
    return f"{ROOT}/{check_fleet(fleet)}/gcs/*/alive"


def gcs_heartbeat(fleet: str, gcs_id: int) -> str:
    """Where station `gcs_id` publishes its signed heartbeats (the routers' access control lets
    only `gcs-*` identities publish here)."""
    return f"{ROOT}/{check_fleet(fleet)}/gcs/{check_vehicle_id(gcs_id)}/heartbeat"


def all_gcs_heartbeats(fleet: str) -> str:
    return f"{ROOT}/{check_fleet(fleet)}/gcs/*/heartbeat"


def parse_gcs_heartbeat_key(key: str) -> tuple[str, int] | None:
    """(fleet, station id) of a heartbeat key, or None if `key` is not one."""
    m = _HEARTBEAT_KEY_RE.match(str(key))
    if not m or not 1 <= int(m.group(2)) <= MAX_VEHICLE_ID:
        return None
    return m.group(1), int(m.group(2))


def gcs_traffic(fleet: str, gcs_id: int) -> str:
    """Where station `gcs_id` publishes traffic reports (intruders it flies or tracks)."""
    return f"{ROOT}/{check_fleet(fleet)}/gcs/{check_vehicle_id(gcs_id)}/traffic"


def vehicle_traffic(fleet: str, vehicle_id: int) -> str:
    """Where vehicle `vehicle_id` publishes the traffic its autopilot's receiver hears."""
    return _msg(fleet, vehicle_id, "traffic")


def all_traffic(fleet: str) -> str:
    """Every traffic report of the fleet, from stations and vehicles alike."""
    return f"{ROOT}/{check_fleet(fleet)}/*/*/traffic"


def roster(fleet: str) -> str:
    """Where a new fleet roster is pushed, and where every keyed member answers with its own."""
    return f"{ROOT}/{check_fleet(fleet)}/roster"


def plan(fleet: str) -> str:
    """Where a new fleet plan is pushed, and where every member answers with the one it holds."""
    return f"{ROOT}/{check_fleet(fleet)}/plan"


def everything(fleet: str) -> str:
    """Every key of one fleet (for the recorder)."""
    return f"{ROOT}/{check_fleet(fleet)}/**"


def parse_vehicle_key(key: str) -> tuple[str, int, str] | None:
    """(fleet, vehicle_id, leaf) of a vehicle key, or None if `key` is not one."""
    parsed = _parse(key)
    return None if parsed is None else parsed[:3]


def parse_state_key(key: str) -> tuple[str, int, Cell | None] | None:
    """(fleet, vehicle_id, cell or None if unplaced) of a state key, or None if not one."""
    parsed = _parse(key)
    if parsed is None or parsed[2] != "state":
        return None
    return parsed[0], parsed[1], parsed[3]


def _parse(key: str) -> tuple[str, int, str, Cell | None] | None:
    key = str(key)
    m = _CELL_STATE_KEY_RE.match(key) or _LEGACY_CELL_STATE_KEY_RE.match(key)
    if m:
        fleet, vid, leaf = m["fleet"], int(m["vid"]), "state"
        cn, ce = int(m["cn"]), int(m["ce"])
        if max(abs(cn), abs(ce)) > MAX_CELL:
            return None
        cell: Cell | None = (cn, ce)
    else:
        m = _VEHICLE_KEY_RE.match(key)
        if not m or m["leaf"] not in _LEAVES[m["ns"]]:
            return None
        fleet, vid, leaf, cell = m["fleet"], int(m["vid"]), m["leaf"], None
    if not 1 <= vid <= MAX_VEHICLE_ID:
        return None
    return fleet, vid, leaf, cell


def parse_gcs_key(key: str) -> tuple[str, int] | None:
    m = _GCS_KEY_RE.match(str(key))
    if not m:
        return None
    return m.group(1), int(m.group(2))
