"""Following the fleet plan on the mesh (`covey/<fleet>/plan`), exactly as the roster is followed.

Every agent, multi-vehicle host and ground station runs one `PlanSync`: a `DocSync`
(trust/roster_sync.py) over `PlanDoc`. A newer plan pushed there (`covey plan push`, the
station's plan panel) is applied at once; members answer `plan?have=<v>` only when they hold a
newer one; a member pulls at start, on every new link and periodically, so a rebooted vehicle
catches up from whoever holds the plan; a member that sees an older plan put re-publishes its
own. What arrives is checked cheapest first: size and header (`PlanMessage.peek`, O(1)), not
newer than the held plan -> dropped unverified, then the signature, then the polygons.

Keyed mode: a plan is applied only if the fleet authority (signer 0) or a station of the current
roster signed it (trust/auth.py `check_plan`). A plan a station signed before it was revoked
stays held by members that applied it; members that check it afterwards refuse it (push a plan
signed by the authority or a current station). Open mode (no key): every well-formed plan is
applied, as every command is; said once when the follower starts.
"""

from __future__ import annotations

import logging
import random
import threading
import time
from collections.abc import Callable

import zenoh

from comms import keys
from comms.doc_sync import (
    Confirmation,
    DocSync,
    Offer,
    RosterSyncConfig,
    confirmations,
    publish_doc,
)
from comms.member import MemberAuth
from comms.plan import FleetPlan
from comms.schema import PlanHead, PlanMessage

log = logging.getLogger(__name__)

START_PULL_S = 1.0
"""A process that starts waits at most this long for the plan from the members that hold it
(`DocSync.pull_now`) before it answers commands: a rebooted vehicle never flies a goto the
fleet's plan refuses."""


class PlanDoc:
    """The fleet plan as a `SignedDoc` (trust/roster_sync.py): the plan this member holds."""

    name = "plan"

    def __init__(self, fleet: str, auth: MemberAuth | None, plan: FleetPlan | None = None) -> None:
        """`auth`: this member's trust.auth.FleetAuth, or None (open mode). `plan`: the plan to
        start from (e.g. read from a file), checked like one that arrives."""
        self.key = keys.plan(fleet)
        self.fleet = fleet
        self.auth = auth
        self._lock = threading.Lock()
        self._plan: FleetPlan | None = None
        self._bytes: bytes | None = None
        if plan is not None:
            data = PlanMessage(plan).encode()
            head = self.peek(data)
            problem = self.genuine(head) if plan.fleet == fleet else f"for fleet {plan.fleet!r}"
            if problem:
                raise ValueError(f"plan v{plan.version}: {problem}")
            self._plan, self._bytes = PlanMessage.decode(data).plan, data

    @property
    def plan(self) -> FleetPlan | None:
        return self._plan

    def peek(self, data: bytes) -> PlanHead:
        return PlanMessage.peek(data)

    def held_version(self) -> int:
        plan = self._plan
        return plan.version if plan is not None else 0

    def genuine(self, head: PlanHead) -> str | None:
        if self.auth is None:
            return None
        return self.auth.check_plan(head.signer_id, head.signed, head.sig)

    def apply(self, data: bytes, head: PlanHead) -> tuple[FleetPlan, str | None]:
        plan = PlanMessage.decode(data).plan
        with self._lock:
            held = self.held_version()
            if plan.version <= held:
                return plan, f"plan v{plan.version} is not newer than v{held}"
            self._plan, self._bytes = plan, bytes(data)
        log.warning(
            "applied fleet plan v%d (signed by %s): %s",
            plan.version,
            "the fleet authority" if plan.signer_id == 0 else f"station {plan.signer_id}",
            describe(plan),
        )
        return plan, None

    def held_bytes(self) -> bytes | None:
        return self._bytes


class PlanSync(DocSync[PlanHead, FleetPlan]):
    """One member's plan follower (see the module docstring); a context manager."""

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        auth: MemberAuth | None,
        cfg: RosterSyncConfig = RosterSyncConfig(),
        *,
        plan: FleetPlan | None = None,
        on_plan: Callable[[FleetPlan], None] | None = None,
        on_summary: Callable[[str], None] | None = None,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        rng: random.Random | None = None,
    ) -> None:
        """`auth`: trust.auth.FleetAuth or None (open mode). `plan`: a plan to start from.
        `on_plan(plan)`: after a newer plan was applied (on a Zenoh or the sync thread)."""
        self.plan_doc = PlanDoc(fleet, auth, plan)
        if auth is None:
            log.warning(
                "OPEN MODE: the fleet plan is not authenticated: anyone on the mesh can replace "
                "the fence and keep-out zones"
            )
        super().__init__(
            session,
            fleet,
            self.plan_doc,
            cfg,
            on_summary=on_summary,
            on_applied=on_plan,
            mono_ns=mono_ns,
            rng=rng,
        )

    @property
    def plan(self) -> FleetPlan | None:
        """The plan held now (None: none yet; the agents' circular fence applies)."""
        return self.plan_doc.plan

    def push(self, plan: FleetPlan) -> Offer:
        """Apply `plan` here (checked as one that arrives) and put it on the mesh if it was
        applied or is the one held."""
        data = PlanMessage(plan).encode()
        result = self.offer(data)
        if result in (Offer.APPLIED, Offer.SAME):
            publish_doc(self.session, self.key, data)
        return result

    def __enter__(self) -> PlanSync:
        return self

    def __exit__(self, *exc: object) -> None:
        self.undeclare()


def publish_plan(session: zenoh.Session, plan: FleetPlan) -> None:
    """Put a (signed) plan on its fleet's plan key, never dropped on a full queue."""
    publish_doc(session, keys.plan(plan.fleet), PlanMessage(plan).encode())


def plan_confirmations(
    session: zenoh.Session, fleet: str, version: int, timeout_s: float = 1.0
) -> list[Confirmation]:
    """Who holds plan `version` or newer (the pusher's check), as `confirmations` for rosters."""
    return confirmations(
        session, fleet, version, timeout_s, key=keys.plan(fleet), peek=PlanMessage.peek
    )


def describe(plan: FleetPlan) -> str:
    """One line: what the plan holds."""
    parts = []
    if plan.fence is not None:
        f = plan.fence
        band = []
        if f.floor_alt_m is not None:
            band.append(f"floor {f.floor_alt_m:g} m")
        if f.ceiling_alt_m is not None:
            band.append(f"ceiling {f.ceiling_alt_m:g} m")
        parts.append(
            f"fence of {len(f.vertices_ne_m)} vertices" + (f" ({', '.join(band)})" if band else "")
        )
    else:
        parts.append("no fence")
    names = ", ".join(repr(z.name) if z.name else "unnamed" for z in plan.keep_out)
    parts.append(f"{len(plan.keep_out)} keep-out zone(s)" + (f" ({names})" if names else ""))
    parts.append(f"{len(plan.rally)} rally point(s)")
    return "; ".join(parts)
