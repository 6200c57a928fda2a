"""The one point-mass model: N vehicles as arrays, advanced by one explicit Euler step.

Every simulator in covey flies its vehicles through `integrate`: the built-in vehicle simulator
behind the agent and `covey fleet-sim` (agent/backends/sim.py), the PX4 emulator
(firmware/sitl/vehicle.py, which adds PX4's modes on top), the policy's evaluation simulator
(policy/evalsim.py, 2-D, ideal or realistic: `VehicleModel`) and its training arenas
(policy/env.py, 2-D, ideal). What differs between them is only how the wanted velocity is
chosen; the physics is this.

Powered rows track their wanted velocity through a first-order velocity loop (time constant
`lag_s`, 0 = at once) with a limited acceleration (the step of the velocity is clipped to
`max_accel_m_s2 * dt_s` as a vector). Unpowered rows in the air fall: gravity down, drag on the
horizontal speed. Rows in 3-D (N, 3) NED stop at the ground (d = 0). A wind (N, 2) moves the
vehicles over the ground on top of the velocity the loop flies (the loop does not reject it).

`VehicleModel` says how real the vehicles are (`ideal`: they fly exactly what is commanded and
know exactly where they are; `realistic`: lag, acceleration limit, gusts and a drifting GNSS
estimate), and `Vehicles` flies N of them: the truth, on which collisions are judged, and the
estimate, which is what a vehicle knows of itself and publishes.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass

import numpy as np

GRAVITY_M_S2 = 9.80665
"""Standard gravity (the one value every model uses)."""
FALL_DRAG_1_S = 0.5
"""Horizontal speed lost per second by a vehicle falling with its motors off."""


def integrate(
    pos_m: np.ndarray,
    vel_m_s: np.ndarray,
    want_vel_m_s: np.ndarray,
    dt_s: float,
    max_accel_m_s2: float | np.ndarray = np.inf,
    powered: np.ndarray | None = None,
    lag_s: float = 0.0,
    wind_m_s: np.ndarray | None = None,
) -> np.ndarray:
    """Advance `pos_m` and `vel_m_s` (N, D) in place by `dt_s`; returns the rows that hit the
    ground in this step, moving down, and were stopped there (N,) bool (always False in 2-D).

    `want_vel_m_s` (N, D): the velocity each powered row tracks. `max_accel_m_s2`: a scalar or
    (N,) limit; inf tracks the wanted velocity exactly (the evaluation simulator). `powered`
    (N,) bool, default all: unpowered rows fall when airborne (3-D) and stand still otherwise.
    A row on the ground stays there unless its new velocity points up (d decreasing).
    `lag_s`: the velocity loop's time constant, dv = (want - v)(1 - exp(-dt / lag)) before the
    acceleration limit (exact for a first-order loop over the step); 0 = no lag. `wind_m_s`
    (N, 2): ground velocity added to the horizontal velocity of airborne (or 2-D) rows.
    """
    n, dims = pos_m.shape
    if powered is None:
        powered = np.ones(n, bool)
    dv = want_vel_m_s - vel_m_s
    if lag_s > 0.0:
        dv = dv * -math.expm1(-dt_s / lag_s)
    limit = np.broadcast_to(np.asarray(max_accel_m_s2, dtype=float) * dt_s, (n,))
    norm = np.linalg.norm(dv, axis=1)
    scale = np.ones(n)
    over = norm > limit
    scale[over] = limit[over] / norm[over]
    if lag_s <= 0.0 and np.all(np.isinf(limit)):
        vel_m_s[powered] = want_vel_m_s[powered]  # exactly the wanted velocity
    else:
        vel_m_s[powered] += dv[powered] * scale[powered, None]
    if dims == 3:
        falling = ~powered & (pos_m[:, 2] < 0.0)
        vel_m_s[falling, :2] *= max(0.0, 1.0 - FALL_DRAG_1_S * dt_s)
        vel_m_s[falling, 2] += GRAVITY_M_S2 * dt_s
        vel_m_s[~powered & ~falling] = 0.0
    else:
        vel_m_s[~powered] = 0.0
    pos_m += vel_m_s * dt_s
    if wind_m_s is not None:
        blown = np.ones(n, bool) if dims != 3 else pos_m[:, 2] < 0.0
        pos_m[blown, :2] += wind_m_s[blown] * dt_s
    if dims != 3:
        return np.zeros(n, bool)
    ground = pos_m[:, 2] >= 0.0
    pos_m[ground, 2] = 0.0
    hit = ground & (vel_m_s[:, 2] > 0.0)
    vel_m_s[hit] = 0.0
    return hit


@dataclass(frozen=True)
class VehicleModel:
    """How real the simulated vehicles are. Each effect is off at its zero value."""

    lag_s: float = 0.0
    """Time constant of the velocity loop (first order): a multirotor reaches 63 % of a new
    velocity setpoint after this long. 0: at once."""
    max_accel_m_s2: float = math.inf
    """Acceleration limit of the velocity loop (inf: none)."""
    gust_m_s: float = 0.0
    """Wind gusts the velocity loop does not reject: 1-sigma per horizontal axis of a
    Gauss-Markov ground velocity added to the flown one."""
    gust_corr_s: float = 5.0
    """Correlation time of the gusts (first-order Gauss-Markov)."""
    drift_m: float = 0.0
    """Error of the position estimate (GNSS): 1-sigma per horizontal axis of a Gauss-Markov
    offset between what the vehicle believes and publishes and where it is. This is the
    1-sigma the vehicle reports as its pos_sigma_m (PX4's eph)."""
    drift_corr_s: float = 10.0
    """Correlation time of the estimate's drift."""
    reported_sigma_m: float | None = None
    """The horizontal 1-sigma the vehicle reports (PX4's eph), where it is not its drift's
    (None: `drift_m`, an honest estimator). An autopilot's accuracy figure is an estimate of
    its own: a conservative one overstates the error (and a vehicle whose autopilot reports
    none is taken at agent/shell_config.py `ShellConfig.assumed_pos_sigma_m`, 0.5 m). Set
    with `drift_m=0` it separates what the filter's uncertainty padding costs from what the
    drift does (bench/berth_floor.py)."""

    def __post_init__(self) -> None:
        for name in ("lag_s", "gust_m_s", "drift_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        r = self.reported_sigma_m
        if r is not None and not (math.isfinite(r) and r >= 0):
            raise ValueError(f"reported_sigma_m must be finite and >= 0 (or unset), got {r}")
        for name in ("gust_corr_s", "drift_corr_s", "max_accel_m_s2"):
            v = getattr(self, name)
            if not v > 0:  # NaN too
                raise ValueError(f"{name} must be > 0, got {v}")

    @property
    def pos_sigma_m(self) -> float:
        """The position 1-sigma these vehicles report: `reported_sigma_m`, else `drift_m`."""
        return self.drift_m if self.reported_sigma_m is None else self.reported_sigma_m

    @classmethod
    def ideal(cls) -> VehicleModel:
        """Vehicles that fly exactly what is commanded and know exactly where they are."""
        return cls()

    @classmethod
    def realistic(cls) -> VehicleModel:
        """A multirotor on plain GNSS: 0.3 s velocity lag, 2.5 m/s^2, 0.2 m/s gusts correlated
        over 5 s, a position estimate 0.5 m off (1-sigma per axis) correlated over 10 s."""
        return cls(
            lag_s=0.3,
            max_accel_m_s2=2.5,
            gust_m_s=0.2,
            gust_corr_s=5.0,
            drift_m=0.5,
            drift_corr_s=10.0,
        )

    @classmethod
    def named(cls, spec: str) -> VehicleModel:
        """A preset, `ideal` or `realistic`, optionally with fields changed after a colon:
        `realistic:drift_m=1.0,gust_m_s=0.4` (the --vehicle-model / --vehicles flags). A bad
        preset, field or value is a ValueError that says which."""
        name, _, rest = str(spec).partition(":")
        name = name.strip()
        if name not in VEHICLE_MODELS:
            raise ValueError(
                f"vehicle model must be one of {', '.join(VEHICLE_MODELS)} (optionally "
                f"followed by :field=value,...), got {spec!r}"
            )
        model = getattr(cls, name)()
        if not rest.strip():
            return model
        fields = [f.name for f in dataclasses.fields(cls)]
        changes: dict[str, float] = {}
        for item in rest.split(","):
            key, eq, value = (x.strip() for x in item.partition("="))
            if key not in fields or not eq:
                raise ValueError(
                    f"vehicle model {spec!r}: {item.strip()!r} is not field=value with a field "
                    f"of {', '.join(fields)}"
                )
            try:
                changes[key] = float(value)
            except ValueError:
                raise ValueError(
                    f"vehicle model {spec!r}: {key} must be a number, got {value!r}"
                ) from None
        try:
            return dataclasses.replace(model, **changes)
        except ValueError as e:
            raise ValueError(f"vehicle model {spec!r}: {e}") from None


VEHICLE_MODELS = ("ideal", "realistic")
"""The named presets of `VehicleModel`."""


def vehicle_model_arg(spec: str) -> str:
    """argparse `type` of the --vehicle-model / --vehicles flags: the spec as given, once
    `VehicleModel.named` takes it (argparse shows its reason otherwise)."""
    try:
        VehicleModel.named(spec)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return spec


def gauss_markov(x: np.ndarray, sigma: float, corr_s: float, dt_s: float, rng) -> None:
    """One step of a first-order Gauss-Markov process in place, stationary at `sigma`:
    x' = a x + sigma sqrt(1 - a^2) w, a = exp(-dt / corr), w ~ N(0, 1)."""
    if sigma <= 0.0:
        return
    a = math.exp(-dt_s / corr_s)
    x *= a
    x += rng.standard_normal(x.shape) * (sigma * math.sqrt(1.0 - a * a))


class Vehicles:
    """N vehicles flown through a `VehicleModel`: `pos_m` / `vel_m_s` are the truth (the loop's
    velocity; the ground velocity adds the gust), `est_pos_m` what each believes (truth +
    drift), `pos_sigma_m` the 1-sigma it reports. Randomness only from the given generator."""

    def __init__(self, pos_m, model: VehicleModel, rng: np.random.Generator, vel_m_s=None):
        self.model = model
        self.rng = rng
        self.pos_m = np.array(pos_m, dtype=np.float64)
        n, dims = self.pos_m.shape
        self.vel_m_s = np.zeros((n, dims)) if vel_m_s is None else np.array(vel_m_s, float)
        # both processes start stationary (a vehicle is already off when it starts); an effect
        # that is off draws nothing, so ideal vehicles leave the caller's random stream alone
        self.gust_m_s = np.zeros((n, 2))
        self.drift_m = np.zeros((n, 2))
        if model.gust_m_s > 0:
            self.gust_m_s = rng.standard_normal((n, 2)) * model.gust_m_s
        if model.drift_m > 0:
            self.drift_m = rng.standard_normal((n, 2)) * model.drift_m

    @property
    def pos_sigma_m(self) -> float:
        return self.model.pos_sigma_m

    @property
    def est_pos_m(self) -> np.ndarray:
        """What each vehicle believes its position is (N, D)."""
        est = self.pos_m.copy()
        est[:, :2] += self.drift_m
        return est

    @property
    def ground_vel_m_s(self) -> np.ndarray:
        """The velocity over the ground (N, D): the loop's plus the gust (what GNSS measures)."""
        v = self.vel_m_s.copy()
        v[:, :2] += self.gust_m_s
        return v

    def step(self, want_vel_m_s, dt_s: float, powered=None) -> np.ndarray:
        """Fly one step of dt_s towards `want_vel_m_s` (N, D); returns `integrate`'s ground hits."""
        m = self.model
        hit = integrate(
            self.pos_m,
            self.vel_m_s,
            np.asarray(want_vel_m_s, dtype=np.float64),
            dt_s,
            m.max_accel_m_s2,
            powered,
            m.lag_s,
            self.gust_m_s if m.gust_m_s > 0 else None,
        )
        gauss_markov(self.gust_m_s, m.gust_m_s, m.gust_corr_s, dt_s, self.rng)
        gauss_markov(self.drift_m, m.drift_m, m.drift_corr_s, dt_s, self.rng)
        return hit
