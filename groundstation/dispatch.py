"""Sending commands from the ground station: addressing, a worker thread, and the kill guard.

`Mesh.send_command` blocks until every vehicle answers or the timeout passes, so the GUI hands
commands to a single worker thread and renders the acks when they arrive; commands go out in the
order they were given.
"""

from __future__ import annotations

import concurrent.futures
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from comms.commands import CommandResult, new_nonce
from comms.mesh import Mesh
from comms.schema import Command, Mission, Role
from groundstation.inputs import CommandRequest
from groundstation.mission_io import MissionRequest

log = logging.getLogger(__name__)


def build_command(
    req: CommandRequest, targets: tuple[int, ...], source_id: int, stamp_ns: int
) -> Command:
    """A wire Command for `req` to `targets` (() = whole fleet)."""
    cmd = Command(
        kind=req.kind,
        nonce=new_nonce(),
        stamp_ns=stamp_ns,
        params=req.params,
        targets=targets,
        source_id=source_id,
    )
    cmd.validate()
    return cmd


def build_mission(
    req: MissionRequest, targets: tuple[int, ...], source_id: int, stamp_ns: int
) -> Mission:
    """A wire Mission for `req` to `targets` (() = whole fleet)."""
    mission = Mission(
        nonce=new_nonce(),
        stamp_ns=stamp_ns,
        items=req.items,
        mission_id=req.mission_id,
        targets=targets,
        source_id=source_id,
    )
    mission.validate()
    return mission


def send(
    mesh: Mesh,
    req: CommandRequest | MissionRequest,
    targets: tuple[int, ...],
    *,
    present: Iterable[int] = (),
    source_id: int = 0,
    timeout_s: float = 2.0,
    on_built: Callable[[Command | Mission], None] | None = None,
) -> CommandResult:
    """Send one command (one query) and collect every answer. For the whole fleet (targets=()),
    every vehicle in `present` is expected to answer, so a silent one shows as a timeout; in
    keyed mode only the roster's vehicles among them (`expected_for_all`).
    `on_built` sees the command (its nonce) before it goes out. A MissionRequest is uploaded
    the same way (one query, an ack per vehicle)."""
    cmd: Command | Mission = (
        build_mission(req, targets, source_id, mesh.clock_ns())
        if isinstance(req, MissionRequest)
        else build_command(req, targets, source_id, mesh.clock_ns())
    )
    if on_built is not None:
        on_built(cmd)
    expect = set(targets) if targets else expected_for_all(present, getattr(mesh, "auth", None))
    return mesh.send_command(cmd, expect=expect, timeout_s=timeout_s)


def expected_for_all(present: Iterable[int], auth) -> set[int]:
    """Which of the `present` vehicles a command to all should wait for: all of them in open
    mode; in keyed mode (`auth`, a trust.auth.FleetAuth) only the vehicles of its roster, since
    anyone can declare a presence token: a flood of fake ones costs no waiting and no rows of
    timeouts (a roster vehicle that is not running shows as not reachable)."""
    if auth is None:
        return set(present)
    return {vid for vid in present if auth.is_member(Role.VEHICLE, vid)}


@dataclass(frozen=True)
class Dispatched:
    """What the GUI shows about one command: what was asked, and (later) the answers."""

    label: str
    results: tuple[CommandResult, ...]
    error: str = ""


class CommandWorker:
    """One background thread that sends commands in order; results go to `on_done`."""

    def __init__(self, on_done: Callable[[Dispatched], None]) -> None:
        self._pool = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="gcs-cmd"
        )
        self._on_done = on_done

    def submit(
        self,
        label: str,
        job: Callable[[], list[CommandResult]],
        on_done: Callable[[Dispatched], None] | None = None,
    ) -> concurrent.futures.Future:
        """Run `job` after the jobs before it; its result goes to the worker's `on_done`, then
        to this submission's own `on_done` (the tab that sent it)."""

        def run() -> None:
            try:
                done = Dispatched(label, tuple(job()))
            except Exception as exc:  # noqa: BLE001 - shown to the operator, not raised into a pool
                log.exception("command %s failed", label)
                done = Dispatched(label, (), error=f"{type(exc).__name__}: {exc}")
            for callback in (self._on_done, on_done):
                if callback is None:
                    continue
                try:
                    callback(done)
                except Exception:  # noqa: BLE001 - a closed tab must not stop the worker
                    log.exception("showing the result of %s failed", label)

        return self._pool.submit(run)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def __enter__(self) -> CommandWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class KillGuard:
    """Two-step kill: `arm(now)` opens a window of `window_s`; only `confirm(now)` inside it
    returns True (and closes it). A single click on either button never kills."""

    def __init__(self, window_s: float = 5.0) -> None:
        self.window_s = window_s
        self._armed_at: float | None = None

    def arm(self, now_s: float) -> None:
        self._armed_at = now_s

    def disarm(self) -> None:
        self._armed_at = None

    def armed(self, now_s: float) -> bool:
        if self._armed_at is not None and now_s - self._armed_at > self.window_s:
            self._armed_at = None
        return self._armed_at is not None

    def remaining_s(self, now_s: float) -> float:
        armed_at = self._armed_at if self.armed(now_s) else None
        return 0.0 if armed_at is None else max(0.0, self.window_s - (now_s - armed_at))

    def confirm(self, now_s: float) -> bool:
        ok = self.armed(now_s)
        self._armed_at = None
        return ok
