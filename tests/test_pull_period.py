"""The fleet documents' periodic pulls stretch with the fleet (comms/doc_sync.py
`pull_period_s`): each member hears about `pulls_heard_per_s` pulls a second however many members
there are, and a member that fell behind still catches up, from the first pull it hears that
holds a newer version.

The rule on its own (pure), then real Zenoh sessions on loopback: a fleet of keyed members pulls
less often than `pull_every_s` once it has heard how many they are, and a member whose own
periodic pull is a minute away catches up from another member's pulls.
"""

from __future__ import annotations

import heapq
import random
import re
import time
from contextlib import ExitStack

import pytest

from comms.doc_sync import RosterSyncConfig, pull_period_s
from comms.mesh import Mesh
from comms.schema import Role
from comms.session import MeshConfig, free_tcp_port
from trust.auth import load_auth
from trust.authority import throwaway_fleet

FLEET = "pulls"
CFG = RosterSyncConfig(pull_every_s=5.0, pulls_heard_per_s=1.0, max_pull_every_s=60.0)


def test_a_small_fleet_keeps_the_shortest_period() -> None:
    # 3 members each pulling every 5 s: 3 pulls heard in 5 s
    assert pull_period_s(3, 5.0, 5.0, CFG) == 5.0
    assert pull_period_s(0, 5.0, 5.0, CFG) == 5.0  # alone, its own pull not delivered back


def test_the_period_grows_with_the_pullers_and_settles_where_each_hears_the_budget() -> None:
    for n in (10, 20, 40, 55):
        period = CFG.pull_every_s
        for _ in range(6):  # every member on the same rule: each hears n pulls a period
            period = pull_period_s(n, period, period, CFG)
        assert period == pytest.approx(max(CFG.pull_every_s, n / CFG.pulls_heard_per_s))
        heard_per_s = n / period
        assert heard_per_s <= CFG.pulls_heard_per_s + 1e-9
    # from a start where everyone pulled twice (start and follow-up) it comes back down
    period = pull_period_s(80, 5.0, 5.0, CFG)
    assert period == 60.0  # 80 pullers estimated: capped
    period = pull_period_s(40, period, period, CFG)  # 40 heard in a whole period of 60 s
    assert period == pytest.approx(40.0)


def test_a_flood_of_queries_cannot_stop_a_members_own_pulls() -> None:
    assert pull_period_s(10**9, 5.0, 5.0, CFG) == CFG.max_pull_every_s


def test_an_empty_window_keeps_the_period_within_its_bounds() -> None:
    assert pull_period_s(5, 0.0, 30.0, CFG) == 30.0
    assert pull_period_s(5, 0.0, 500.0, CFG) == 60.0
    assert pull_period_s(-1, 5.0, 1.0, CFG) == 5.0


@pytest.mark.parametrize(
    "kwargs, says",
    [
        ({"pulls_heard_per_s": 0.0}, "pulls_heard_per_s=0.0 must be within"),
        ({"max_pull_every_s": 1e9}, "max_pull_every_s=1000000000.0 must be within"),
        (
            {"pull_every_s": 10.0, "max_pull_every_s": 5.0},
            "max_pull_every_s=5.0 must be at least pull_every_s=10.0",
        ),
    ],
)
def test_bad_settings_are_refused_with_the_reason(kwargs, says) -> None:
    with pytest.raises(ValueError, match=re.escape(says)):
        RosterSyncConfig(**kwargs)


def simulated_fleet(n: int, join_spread_s: float, seed: int, watch_s: float = 300.0):
    """n members on `pull_period_s`, each joining at a random time within `join_spread_s` and
    then pulling on its own jittered period, every pull heard by every member that has joined
    (one event loop, no Zenoh): (pulls each member heard a second over the last `watch_s` of
    900 s, the periods at the end)."""
    rng = random.Random(seed)
    joins = sorted(rng.uniform(0.0, join_spread_s) for _ in range(n))
    period = [CFG.pull_every_s] * n
    heard, window, late = [0] * n, list(joins), [0] * n
    events = [(t, i) for i, t in enumerate(joins)]
    heapq.heapify(events)
    end_s = 900.0
    while events and events[0][0] <= end_s:
        t, i = heapq.heappop(events)
        for k, joined in enumerate(joins):
            if joined <= t:
                heard[k] += 1
                late[k] += t >= end_s - watch_s
        if t - window[i] >= CFG.pull_every_s:
            period[i] = pull_period_s(heard[i], t - window[i], period[i], CFG)
            heard[i], window[i] = 0, t
        heapq.heappush(events, (t + period[i] * rng.uniform(0.8, 1.2), i))
    return [x / watch_s for x in late], period


@pytest.mark.parametrize("join_spread_s", [0.0, 300.0])
def test_each_member_of_a_fleet_hears_the_budget_however_it_joined(join_spread_s) -> None:
    rates, periods = simulated_fleet(40, join_spread_s, seed=7)
    # before: 40 / 5 = 8 pulls a second each
    assert all(abs(r - CFG.pulls_heard_per_s) < 0.15 for r in rates), rates
    assert all(CFG.pull_every_s <= p <= CFG.max_pull_every_s for p in periods), periods
    rates, periods = simulated_fleet(5, join_spread_s, seed=8)  # a small fleet keeps 5 s
    assert all(p <= CFG.pull_every_s * 1.5 for p in periods), periods
    assert all(r <= 5 / CFG.pull_every_s + 0.1 for r in rates), rates


def test_beyond_the_cap_each_member_hears_the_fleet_over_the_longest_period() -> None:
    rates, periods = simulated_fleet(150, 100.0, seed=9)
    assert all(p == CFG.max_pull_every_s for p in periods)
    assert all(abs(r - 150 / CFG.max_pull_every_s) < 0.3 for r in rates), rates  # not 150 / 5


# -- real sessions ---------------------------------------------------------------------------------
def wait_for(pred, timeout_s: float) -> float | None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if pred():
            return time.monotonic() - t0
        time.sleep(0.02)
    return None


def _fleet(tmp_path, n: int):
    authority = throwaway_fleet(
        tmp_path / "keys", FLEET, vehicles=list(range(1, n + 1)), stations=[1, 2]
    )
    port = free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    return authority, ep, MeshConfig(fleet=FLEET, mode="router", connect=(), listen=(ep,))


def test_a_fleet_pulls_less_often_once_it_has_heard_how_many_they_are(tmp_path) -> None:
    """8 keyed members asked to pull every 0.2 s and to hear 2 pulls a second: after their
    first window they pull about every 8 / 2 = 4 s, not 5 times a second."""
    n, watch_s = 8, 6.0
    cfg = RosterSyncConfig(pull_every_s=0.2, pulls_heard_per_s=2.0, max_pull_every_s=60.0)
    authority, ep, router_cfg = _fleet(tmp_path, n)
    with ExitStack() as stack:
        stack.enter_context(Mesh(router_cfg))
        members = [
            stack.enter_context(
                Mesh(
                    MeshConfig(fleet=FLEET, mode="client", connect=(ep,)),
                    auth=load_auth(str(authority.member_path(Role.VEHICLE, v))),
                    roster_sync=cfg,
                )
            )
            for v in range(1, n + 1)
        ]
        time.sleep(watch_s)
        pulls = [m.roster_sync.counts().get("pulls", 0) for m in members]
        periods = [m.roster_sync._period_s for m in members]
    # Unstretched: watch_s / 0.2 = 30 pulls each. Stretched: the start, a follow-up on the new
    # link, the first periodic ones before the first window closed, then one every ~4 s.
    assert all(p >= 1 for p in pulls), pulls
    assert max(pulls) <= 10, pulls
    assert all(p > 1.0 for p in periods), periods
    print(f"pulls per member in {watch_s:g} s: {pulls}; periods {[round(p, 1) for p in periods]}")


def test_a_member_behind_catches_up_from_another_members_pull(tmp_path) -> None:
    """A holds the old roster and will not pull for a minute; B starts from a key file that
    holds the new one (never pushed). A hears B's pulls, which say B holds a newer version,
    pulls at once, and B answers it. A gets no new link of its own (a client of the router)."""
    authority, ep, router_cfg = _fleet(tmp_path, 2)
    slow = RosterSyncConfig(pull_every_s=60.0)
    quick = RosterSyncConfig(pull_every_s=0.5, max_pull_every_s=0.5)
    a_auth = load_auth(str(authority.member_path(Role.VEHICLE, 1)))
    with (
        Mesh(router_cfg),
        Mesh(
            MeshConfig(fleet=FLEET, mode="client", connect=(ep,)), auth=a_auth, roster_sync=slow
        ) as a,
    ):
        assert wait_for(lambda: a.roster_sync.counts().get("pulls", 0) >= 1, 5)
        authority.revoke(Role.STATION, 2)
        held = load_auth(str(authority.member_path(Role.STATION, 1)))
        assert a.auth.roster.version < held.roster.version
        b_auth = load_auth(str(authority.member_path(Role.VEHICLE, 2)))
        old_b = b_auth.roster.version
        with Mesh(
            MeshConfig(fleet=FLEET, mode="client", connect=(ep,)), auth=b_auth, roster_sync=quick
        ) as b:
            assert b.auth.roster.version == held.roster.version  # read from its key file
            pulls_before = a.roster_sync.counts().get("pulls", 0)
            took = wait_for(lambda: a.auth.roster.version == held.roster.version, 10)
            assert took is not None, (a.roster_sync.counts(), b.roster_sync.counts())
        assert not a.auth.is_member(Role.STATION, 2)
        assert a.roster_sync.counts()["pulls"] > pulls_before  # it pulled, on hearing B
        assert old_b == held.roster.version
    print(f"caught up {took:.2f} s after the member ahead joined")
