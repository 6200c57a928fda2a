"""Failsafes with injected time."""

from __future__ import annotations

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
