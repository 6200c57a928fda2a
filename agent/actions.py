"""A vehicle's action queue: autopilot calls run here, never on the tick or the command thread.

A MAVSDK take-off is up to three autopilot calls of up to 6 s each; a relay command up to three
tries of 1 s. The agent answers a command as soon as the mode machine accepts it and hands the
autopilot's part to this queue, so the tick keeps flying and publishing states meanwhile. Actions
run one at a time, in order, on the queue's own thread. A kill does not wait: it runs at once on
a thread of its own and drops what was still waiting (reported as not run). Each action's outcome
goes to `on_outcome(action, error)` (error None: done).
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable

from agent.backends.base import VehicleBackend
from agent.flight_core import Action, ActionKind
from comms.schema import ActionOutcome, Mode

log = logging.getLogger(__name__)

Outcome = Callable[[Action, "str | None"], None]


class ActionQueue:
    """One vehicle's autopilot actions, in order, off the caller's thread. A context manager."""

    def __init__(
        self,
        run: Callable[[Action], None],
        on_outcome: Outcome,
        name: str = "actions",
        *,
        threaded: bool = True,
    ) -> None:
        """`threaded` False runs each action at once on the caller's thread: for simulated
        autopilots whose calls take microseconds (covey fleet-sim)."""
        self._run = run
        self._on_outcome = on_outcome
        self._pending: collections.deque[Action] = collections.deque()
        self._cv = threading.Condition()
        self._closed = False
        self._busy = False
        self._threaded = threaded
        self._thread = threading.Thread(target=self._worker, name=name, daemon=True)
        if threaded:
            self._thread.start()

    def __enter__(self) -> ActionQueue:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pending(self) -> int:
        with self._cv:
            return len(self._pending)

    @property
    def busy(self) -> bool:
        """An action waits or runs."""
        with self._cv:
            return bool(self._pending) or self._busy

    def submit(self, action: Action) -> None:
        if not self._threaded:
            self._execute(action)
            return
        if action.kind is ActionKind.KILL:
            with self._cv:
                dropped = list(self._pending)
                self._pending.clear()
            for a in dropped:
                self._report(a, "not run: the vehicle was killed first")
            threading.Thread(target=self._execute, args=(action,), name="kill", daemon=True).start()
            return
        with self._cv:
            if self._closed:
                dropped = [action]
            else:
                dropped = []
                self._pending.append(action)
                self._cv.notify()
        for a in dropped:
            self._report(a, "not run: the agent is shutting down")

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop taking actions; what still waits is reported as not run."""
        with self._cv:
            self._closed = True
            dropped = list(self._pending)
            self._pending.clear()
            self._cv.notify_all()
        for a in dropped:
            self._report(a, "not run: the agent is shutting down")
        if self._threaded:
            self._thread.join(timeout_s)

    def _worker(self) -> None:
        while True:
            with self._cv:
                while not self._pending and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                action = self._pending.popleft()
                self._busy = True
            try:
                self._execute(action)
            finally:
                with self._cv:
                    self._busy = False
                    self._cv.notify_all()

    def wait_idle(self, timeout_s: float) -> bool:
        """Block until nothing waits or runs (True), or the timeout passes (False)."""
        with self._cv:
            return self._cv.wait_for(lambda: not self._pending and not self._busy, timeout_s)

    def _execute(self, action: Action) -> None:
        try:
            self._run(action)
        except Exception as exc:  # noqa: BLE001 - every failure is an outcome, never a dead thread
            self._report(action, str(exc) or type(exc).__name__)
            return
        self._report(action, None)

    def _report(self, action: Action, error: str | None) -> None:
        try:
            self._on_outcome(action, error)
        except Exception:  # noqa: BLE001 - a broken reporter must not stop the queue
            log.exception("action outcome handler failed")


def perform(action: Action, backend: VehicleBackend) -> None:
    """Run one action on a vehicle (the queue's worker calls this; errors are outcomes)."""
    if action.kind is ActionKind.TAKEOFF:
        backend.takeoff(action.alt_m)
    elif action.kind is ActionKind.LAND:
        backend.land()
    elif action.kind is ActionKind.HOLD:
        backend.hold()
    elif action.kind is ActionKind.KILL:
        backend.kill()
    elif action.target_global is not None and backend.takes_global_targets:
        backend.goto_global(*action.target_global)
    elif action.target_ned_m is not None:
        backend.goto_local(action.target_ned_m)
    else:
        raise ValueError(f"{action.kind.name} without a target")


def outcome_of(
    action: Action,
    vehicle_id: int,
    error: str | None,
    back_to: Mode | None = None,
    stamp_ns: int = 0,
) -> ActionOutcome:
    """What the station is told when `action` (asked for by a command) has ended, at
    `stamp_ns` (the vehicle's clock)."""
    detail = action.describe()
    if error is not None:
        detail = f"{detail}: {error}" + (
            f"; back to {back_to.name.lower()}" if back_to is not None else ""
        )
    return ActionOutcome(vehicle_id, action.nonce or 0, error is None, detail, stamp_ns)
