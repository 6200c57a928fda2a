"""The reach check before a signature check (comms/gate.py step 4b, NeighbourTable.worth_checking):
states from beyond the agent's reach are dropped unverified, and no forged state can use that to
keep a real one out or to push a held neighbour out of the table."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from agent.neighbours import NeighbourTable
from comms.gate import SKIPPED, Gate, GateConfig, Refusal
from comms.schema import Mode, Role, VehicleState
from trust.auth import FleetAuth, load_auth
from trust.authority import Authority, throwaway_fleet

T0_NS = time.time_ns()
MS = 10**6
REACH_M = 21.0


@pytest.fixture
def fleet(tmp_path) -> Authority:
    return throwaway_fleet(tmp_path / "keys", "covey", vehicles=range(1, 5), stations=[1])


def member(fleet: Authority, vid: int) -> FleetAuth:
    return load_auth(str(fleet.member_path(Role.VEHICLE, vid)))


def state(vid: int, seq: int, ne_m: tuple[float, float]) -> VehicleState:
    return VehicleState(
        vid, seq, T0_NS + seq * 100 * MS, (*ne_m, -10.0), (0.0, 0.0, 0.0), 0.0, Mode.GOTO, True
    )


class Receiver:
    """Vehicle 1's side: its table (reach centred at the origin) behind one gate, as the agent
    wires them (comms/mesh.py: the gate, then `table.update` for what it accepts)."""

    def __init__(self, fleet: Authority) -> None:
        self.table = NeighbourTable(1, reach_m=REACH_M)
        self.table.snapshot(0.0, np.zeros(3))  # the agent's tick: the reach centred here
        self.gate = Gate(member(fleet, 1), GateConfig(), worth_checking=self.table.worth_checking)

    def offer(self, s: VehicleState):
        recv_ns = s.stamp_ns + MS
        verdict = self.gate.admit_state(s, recv_ns)
        if verdict is None:
            self.table.update(s, recv_ns / 1e9)
        return verdict


def test_states_beyond_reach_are_skipped_unverified_and_within_it_checked(fleet) -> None:
    rx, v2, v3 = Receiver(fleet), member(fleet, 2), member(fleet, 3)
    assert rx.offer(v2.sign_state(state(2, 1, (40.0, 0.0)))) is SKIPPED  # beyond: no check
    assert rx.gate.out_of_reach == 1 and rx.gate.accepted == 0
    # a forged far state costs no check either, and is not in the table
    assert rx.offer(v3.sign_state(state(2, 2, (0.0, 45.0)))) is SKIPPED
    assert 2 not in rx.table.latest()
    # within reach: checked; the real one accepted, a forged one refused
    assert rx.offer(v2.sign_state(state(2, 3, (15.0, 0.0)))) is None
    assert rx.offer(v3.sign_state(state(2, 4, (14.0, 0.0)))) is Refusal.FORGED
    assert rx.table.latest()[2].seq == 3 and rx.gate.accepted == 1


def test_a_held_neighbour_that_leaves_is_forgotten_and_a_forger_cannot_make_it_so(fleet) -> None:
    rx, v2, v3 = Receiver(fleet), member(fleet, 2), member(fleet, 3)
    assert rx.offer(v2.sign_state(state(2, 1, (10.0, 0.0)))) is None
    # A forged "far away" state of the held neighbour is checked (it is held within reach) and
    # refused: the neighbour stays where its real state put it.
    assert rx.offer(v3.sign_state(state(2, 2, (60.0, 0.0)))) is Refusal.FORGED
    assert rx.table.latest()[2].pos_ned_m[0] == 10.0
    # A tampered copy of a real state, moved out of reach: refused too.
    moved = dataclasses.replace(v2.sign_state(state(2, 3, (11.0, 0.0))), pos_ned_m=(70, 0, -10))
    assert rx.offer(moved) is Refusal.FORGED and 2 in rx.table.latest()
    # Its real state beyond reach: checked (it is held), accepted, and the table lets it go.
    assert rx.offer(v2.sign_state(state(2, 4, (30.0, 0.0)))) is None
    assert 2 not in rx.table.latest()
    # From then on its far states are skipped unverified, until it comes back within reach.
    assert rx.offer(v2.sign_state(state(2, 5, (35.0, 0.0)))) is SKIPPED
    assert rx.offer(v2.sign_state(state(2, 6, (18.0, 0.0)))) is None
    assert rx.table.latest()[2].seq == 6


def test_the_reach_moves_with_the_vehicle_and_none_means_everything(fleet) -> None:
    table = NeighbourTable(1, reach_m=REACH_M)
    far = member(fleet, 2).sign_state(state(2, 1, (100.0, 0.0)))
    assert table.worth_checking(far)  # not yet known where we are: hear everything
    table.snapshot(0.0, np.array([90.0, 0.0, -10.0]))
    assert table.worth_checking(far)
    table.snapshot(0.0, np.array([0.0, 0.0, -10.0]))
    assert not table.worth_checking(far)
    assert NeighbourTable(1).worth_checking(far)  # no reach: every state is checked
    with pytest.raises(ValueError, match="reach_m"):
        NeighbourTable(1, reach_m=float("nan"))
