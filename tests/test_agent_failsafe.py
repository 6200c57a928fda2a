"""Failsafes with injected time."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from agent.failsafe import FailsafeConfig, Failsafes
from agent.modes import Trigger
from comms.schema import Mode, StateFlag

HERE = np.array([0.0, 0.0, -10.0])


def test_ground_station_loss_holds_then_lands() -> None:
    fs = Failsafes(FailsafeConfig(gcs_lost_hold_s=2.0, gcs_lost_land_s=6.0), now_s=0.0)
    assert fs.evaluate(1.0, Mode.GOTO, True, 90.0, HERE) is None
    assert fs.evaluate(2.5, Mode.GOTO, False, 90.0, HERE) is None
    hold = fs.evaluate(3.1, Mode.GOTO, False, 90.0, HERE)
    assert hold.trigger is Trigger.FAILSAFE_HOLD
    assert fs.flags & StateFlag.FAILSAFE_GCS_LOST
    assert fs.evaluate(5.0, Mode.HOLDING, False, 90.0, HERE) is None
    land = fs.evaluate(7.1, Mode.HOLDING, False, 90.0, HERE)
    assert land.trigger is Trigger.FAILSAFE_LAND
    assert fs.evaluate(8.0, Mode.LANDING, False, 90.0, HERE) is None


def test_ground_station_return_ends_the_hold() -> None:
    fs = Failsafes(FailsafeConfig(gcs_lost_hold_s=1.0, gcs_lost_land_s=10.0), now_s=0.0)
    assert fs.evaluate(1.5, Mode.GOTO, False, 90.0, HERE).trigger is Trigger.FAILSAFE_HOLD
    assert fs.gcs_failsafe_active
    assert fs.gcs_back(2.0) is True
    assert not fs.flags & StateFlag.FAILSAFE_GCS_LOST
    assert fs.evaluate(2.5, Mode.GOTO, True, 90.0, HERE) is None


def test_landed_vehicles_ignore_ground_station_loss() -> None:
    fs = Failsafes(FailsafeConfig(gcs_lost_hold_s=1.0, gcs_lost_land_s=2.0), now_s=0.0)
    assert fs.evaluate(100.0, Mode.LANDED, False, 90.0, HERE) is None


def test_battery_returns_then_lands() -> None:
    fs = Failsafes(FailsafeConfig(require_gcs=False), now_s=0.0)
    assert fs.evaluate(1.0, Mode.GOTO, False, 24.0, HERE).trigger is Trigger.FAILSAFE_RETURN
    assert fs.evaluate(2.0, Mode.RETURNING, False, 20.0, HERE) is None
    assert fs.evaluate(3.0, Mode.RETURNING, False, 9.0, HERE).trigger is Trigger.FAILSAFE_LAND


def test_leaving_the_geofence_holds() -> None:
    cfg = FailsafeConfig(require_gcs=False, geofence_radius_m=50.0)
    fs = Failsafes(cfg, now_s=0.0)
    action = fs.evaluate(1.0, Mode.GOTO, True, 90.0, np.array([40.0, 40.0, -10.0]))
    assert action.trigger is Trigger.FAILSAFE_HOLD and "geofence" in action.reason
    assert fs.flags & StateFlag.GEOFENCE


@pytest.mark.parametrize(
    ("target", "why"),
    [((0, 0, -0.2), "altitude"), ((0, 0, -500), "altitude"), ((400, 400, -10), "geofence")],
)
def test_targets_outside_limits_are_refused(target, why) -> None:
    assert why in FailsafeConfig(geofence_radius_m=500.0).check_target(
        np.array(target, dtype=float)
    )
    assert FailsafeConfig().check_target(np.array([10.0, 10.0, -10.0])) is None


def _inner(fs: Failsafes) -> tuple:
    return (fs._gcs_seen_s, fs._gcs_failsafe, fs._battery_acted, fs._fence_tripped, fs.flags)


@pytest.mark.parametrize("seed", range(4))
def test_the_calm_shortcut_is_what_evaluate_does(seed) -> None:
    """The flight core skips `evaluate` for calm rows of settled vehicles and only notes the
    station: on random histories (station losses, low batteries, fence exits, every mode) that
    is exactly what evaluate returns and leaves behind, and calm never covers a row where
    evaluate would act."""
    rng = np.random.default_rng(seed)
    cfg = FailsafeConfig(geofence_radius_m=float(rng.choice([0.0, 40.0])))
    n = 40
    fleet = [Failsafes(cfg, 0.0) for _ in range(n)]
    shortcut_taken = 0
    for tick in range(300):
        now_s = tick * 0.5
        gcs_alive = bool(rng.random() > 0.1)
        battery = rng.choice([100.0, 60.0, 26.0, 25.0, 12.0, 9.0, np.nan], n)
        pos = rng.normal(0.0, 30.0, (n, 3))
        calm = cfg.calm_rows(gcs_alive, battery, pos)
        for i, fs in enumerate(fleet):
            mode = Mode(int(rng.choice([m.value for m in Mode])))
            if calm[i] and fs.settled:
                reference = copy.deepcopy(fs)
                assert reference.evaluate(now_s, mode, gcs_alive, float(battery[i]), pos[i]) is None
                fs.saw_gcs(now_s)
                assert _inner(fs) == _inner(reference)
                shortcut_taken += 1
            else:
                fs.evaluate(now_s, mode, gcs_alive, float(battery[i]), pos[i])
    assert shortcut_taken > 1000  # the shortcut was exercised, not just the slow path
