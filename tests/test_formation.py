"""groundstation/formation.py: slots of each shape, the optimal assignment (against a brute force),
every refusal with its reason, and a moved formation that keeps each vehicle's slot."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest

from comms.plan import Fence, FleetPlan, Zone
from groundstation.formation import (
    FormationError,
    FormationMemory,
    FormationSpec,
    assign,
    closest_pair,
    load_slots,
    plan_formation,
    slots_ned_m,
)
from kit.safe_load import BadFileError


def _spec(shape: str = "circle", **kw) -> FormationSpec:
    base = {"spacing_m": 5.0, "center_ne_m": (10.0, -4.0), "alt_m": 12.0}
    return FormationSpec(shape, **(base | kw))


@pytest.mark.parametrize("shape", ["grid", "line", "circle", "v"])
@pytest.mark.parametrize("n", [1, 2, 5, 8, 13])
def test_generated_shapes_are_spaced_and_centred(shape: str, n: int) -> None:
    spec = _spec(shape, heading_deg=37.0)
    slots = slots_ned_m(spec, n)
    assert slots.shape == (n, 3)
    assert np.allclose(slots[:, 2], -12.0)
    assert np.allclose(slots[:, :2].mean(axis=0), (10.0, -4.0))
    if n > 1:
        d = closest_pair(slots)[2]
        assert d == pytest.approx(5.0, abs=1e-9) or d > 5.0


def test_heading_turns_the_shape_rigidly() -> None:
    a = slots_ned_m(_spec("line", heading_deg=0.0), 3)
    b = slots_ned_m(_spec("line", heading_deg=90.0), 3)
    # heading 0: a line across north, i.e. along east; heading 90: along north
    assert np.allclose(a[:, 0], 10.0) and np.allclose(np.diff(a[:, 1]), 5.0)
    assert np.allclose(b[:, 1], -4.0) and np.allclose(np.diff(b[:, 0]), -5.0)


def test_v_points_along_the_heading() -> None:
    slots = slots_ned_m(_spec("v", center_ne_m=(0.0, 0.0)), 5)
    assert int(np.argmax(slots[:, 0])) == 0  # the apex is the northmost slot
    assert np.allclose(sorted(slots[1:, 1]), sorted(-slots[1:, 1]))  # two mirrored wings


def _brute_force(pos: np.ndarray, slots: np.ndarray) -> float:
    n = len(pos)
    return min(
        sum(float(((pos[i] - slots[p[i]]) ** 2).sum()) for i in range(n))
        for p in itertools.permutations(range(n))
    )


@pytest.mark.parametrize("seed", range(12))
def test_assignment_is_optimal_against_a_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 8))
    pos = rng.uniform(-30, 30, (n, 3))
    slots = rng.uniform(-30, 30, (n, 3))
    slot_of = assign(pos, slots)
    assert sorted(slot_of.tolist()) == list(range(n))
    cost = float(((pos - slots[slot_of]) ** 2).sum())
    assert cost == pytest.approx(_brute_force(pos, slots), rel=1e-12)


def test_optimal_assignment_uncrosses_paths() -> None:
    """Two vehicles whose nearest-first choice would cross are given the parallel paths."""
    pos = {1: (0.0, 0.0, -10.0), 2: (0.0, 10.0, -10.0)}
    spec = _spec("line", center_ne_m=(20.0, 5.0), alt_m=10.0, spacing_m=10.0)
    fp = plan_formation(spec, pos, 3.0)
    # slot 0 is west (E 0), slot 1 east (E 10): vehicle 1 (west) takes the west slot
    assert fp.targets_ned_m[0].tolist() == [20.0, 0.0, -10.0]
    assert fp.targets_ned_m[1].tolist() == [20.0, 10.0, -10.0]


def _grid_positions(n: int, rng: np.random.Generator) -> dict[int, tuple[float, float, float]]:
    pts = [(8.0 * (k // 4), 8.0 * (k % 4), -6.0) for k in range(n)]
    ids = rng.permutation(np.arange(1, n + 1)).tolist()
    return dict(zip(ids, pts, strict=True))


def test_moving_a_formation_keeps_each_vehicles_slot() -> None:
    rng = np.random.default_rng(3)
    pos = _grid_positions(8, rng)
    memory = FormationMemory()
    first = plan_formation(_spec("line"), pos, 3.0, memory=memory)
    assert not first.kept
    # fly there, then turn the line by 180 degrees: the optimal assignment would swap the ends
    there = dict(zip(first.vehicle_ids, map(tuple, first.targets_ned_m), strict=True))
    turned = _spec("line", heading_deg=180.0, center_ne_m=(30.0, 0.0))
    moved = plan_formation(turned, there, 3.0, memory=memory)
    assert moved.kept and moved.slot_of == first.slot_of
    fresh = plan_formation(turned, there, 3.0)
    assert fresh.slot_of != first.slot_of  # so keeping them is a choice, not a coincidence
    again = plan_formation(turned, there, 3.0, memory=memory, reassign=True)
    assert not again.kept and again.slot_of == fresh.slot_of
    # the memory survives covey cmd's state file; another spacing is another formation
    restored = FormationMemory.from_json(memory.to_json())
    assert plan_formation(_spec("line"), there, 3.0, memory=restored).kept
    assert not plan_formation(_spec("line", spacing_m=6.0), there, 3.0, memory=restored).kept
    assert FormationMemory.from_json("{not json").recall("x") is None


def test_refusals_say_why() -> None:
    pos = {1: (0.0, 0.0, -5.0), 2: (5.0, 0.0, -5.0), 3: (0.0, 5.0, -5.0)}
    cases = [
        (lambda: plan_formation(_spec(spacing_m=2.0), pos, 3.0), "closer than the 3 m separation"),
        (lambda: plan_formation(_spec(), {}, 3.0), "no vehicles"),
        (lambda: plan_formation(_spec(), pos | {4: None}, 3.0), "no position yet from vehicle 4"),
        (
            lambda: plan_formation(
                _spec("file", file_slots_fr_m=((0, 0), (0, 5), (0, 10), (0, 15))), pos, 3.0
            ),
            "4 slots for 3 vehicles: more slots than vehicles",
        ),
        (
            lambda: plan_formation(_spec("file", file_slots_fr_m=((0, 0), (0, 5))), pos, 3.0),
            "2 slots for 3 vehicles: more vehicles than slots",
        ),
        (lambda: _spec("star"), "choose one of grid, line, circle, v, file"),
        (lambda: _spec(spacing_m=-1.0), "--spacing-m: must be positive"),
        (lambda: _spec(alt_m=0.0), "--alt-m: 0 m must be above the origin"),
        (lambda: _spec(heading_deg=math.nan), "--heading-deg: must be a finite number"),
        (lambda: _spec("file"), "shape 'file' needs --slots FILE"),
        (lambda: _spec("grid", file_slots_fr_m=((0, 0),)), "--slots is for shape 'file'"),
    ]
    for call, why in cases:
        with pytest.raises(FormationError, match=None) as exc:
            call()
        assert why in str(exc.value), (why, str(exc.value))


def test_fleet_plan_refuses_slots_outside_the_fence_or_in_a_zone() -> None:
    pos = {1: (0.0, 0.0, -5.0), 2: (5.0, 0.0, -5.0), 3: (0.0, 5.0, -5.0)}
    square = ((-50.0, -50.0), (-50.0, 50.0), (50.0, 50.0), (50.0, -50.0))
    school = Zone(((5.0, -10.0), (5.0, 0.0), (15.0, 0.0), (15.0, -10.0)), name="school")
    plan = FleetPlan("covey", 1, 0, fence=Fence(square, ceiling_alt_m=30.0), keep_out=(school,))
    with pytest.raises(FormationError, match="inside keep-out zone 'school'"):
        plan_formation(_spec(center_ne_m=(10.0, -5.0)), pos, 3.0, plan=plan)
    with pytest.raises(FormationError, match="outside the fence"):
        plan_formation(_spec(center_ne_m=(48.0, 0.0)), pos, 3.0, plan=plan)
    with pytest.raises(FormationError, match="above the 30 m ceiling"):
        plan_formation(_spec(center_ne_m=(30.0, 30.0), alt_m=40.0), pos, 3.0, plan=plan)
    ok = plan_formation(_spec(center_ne_m=(30.0, 30.0)), pos, 3.0, plan=plan)
    assert len(ok.lines()) == 3 and "slot" in ok.lines()[0]


def test_slot_file(tmp_path) -> None:
    good = tmp_path / "slots.json"
    good.write_text(json.dumps({"slots_fr_m": [[0, 0], [0, 5], [5, 0]]}))
    assert load_slots(str(good)) == ((0.0, 0.0), (0.0, 5.0), (5.0, 0.0))
    for body, why in [
        ("[1, 2]", "expected"),
        (json.dumps({"slots_fr_m": [[0, "a"]]}), "slot 0 is"),
        (json.dumps({"slots_fr_m": [[0, 1e9]]}), "within 10 km"),
        (json.dumps({"slots_fr_m": [[0, 0]] * 2000}), "at most 1024"),
    ]:
        good.write_text(body)
        with pytest.raises(FormationError, match=why):
            load_slots(str(good))
    good.write_text("{" * 100)
    with pytest.raises(BadFileError, match="nests deeper"):
        load_slots(str(good))
    with pytest.raises(BadFileError, match="does not exist"):
        load_slots(str(tmp_path / "none.json"))


def test_foxglove_draws_each_vehicles_leg_to_its_slot() -> None:
    """A recording or the live bridge shows a formation: each vehicle's goal (its slot) as a
    sphere and the leg to it as a line, decoded with protobuf from the channel's own schema."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    from comms import schema
    from recording import foxglove_channels as fc

    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(fc.SCENE_UPDATE.data).file:
        pool.Add(fd)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(fc.SCENE_UPDATE.name))
    s = schema.VehicleState(
        3, 1, 10**9, (1.0, 2.0, -5.0), (0.5, 0.0, 0.0), 0.0, schema.Mode.GOTO, True, 90.0,
        schema.StateFlag.HAS_GOAL, (10.0, 2.0, -6.0),
    )  # fmt: skip
    out = fc.Converter().state(s, 10**9)
    update = cls.FromString(next(o.data for o in out if o.topic == fc.SCENE_TOPIC))
    (entity,) = update.entities
    (line,) = entity.lines
    assert [(p.x, p.y, p.z) for p in line.points] == [(1.0, 2.0, -5.0), (10.0, 2.0, -6.0)]
    assert len(entity.spheres) == 1
    s_no_goal = schema.VehicleState(4, 1, 10**9, (1.0, 2.0, -5.0), (0.0, 0.0, 0.0), 0.0)
    update = cls.FromString(
        next(o.data for o in fc.Converter().state(s_no_goal, 10**9) if o.topic == fc.SCENE_TOPIC)
    )
    assert not update.entities[0].lines
