"""Numpy runtime of the guidance policy (no torch): what the agents run.

    pol = GuidancePolicy.load()                 # shipped weights, flown as the agents fly them
    v_m_s = pol.command(pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad)

or, with the decision hold: `held = pol.preferred(...)` every `pol.decision_period_s`, and
`pol.filter(pos_m, vel_m_s, held, nbr_pos_m, nbr_vel_m_s)` every tick. N vehicles at once:
`pol.command_batch(obs)` with a policy.observation.Observations (each vehicle's own view) or a
Swarm (every vehicle sees every other).

Those are the ways in. Inside, one vehicle travels as a policy.observation.Observation:
policy.actor runs the network on it (policy.network), this module turns the action into a
velocity, then the sparse rule (policy.sparse) and the filter (policy.safety).

World frame: x north, y east, metres; heading 0 = north, clockwise positive.
The contract is docs/POLICY_SPEC.md; observations come from policy.features.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from kit.safe_load import parse_json
from policy import features, safety, sparse
from policy.actor import Actor
from policy.features import ObsConfig
from policy.network import Network, load_weight_arrays
from policy.observation import EXACT, Observation, Observations, Sky, Swarm, check_array
from policy.zone_lines import ZoneSet

DEFAULT_WEIGHTS = Path(__file__).parent / "weights" / "policy.npz"


LEGACY_FILTERED_TOLD_SHARE = 1.25 / 3.0
"""The share of the separation flight tells weights whose config states none (3 m -> 1.25 m),
with the separation filter on: the network then keeps a narrower berth than the paper's and
leaves the separation itself to the filter. Chosen for the weights shipped before issue 35's
fine-tune on drifting estimates, on seeds the repository had not used (docs/policy.md, "The
policy's berth"): conflicts 1.25 -> 1.09-1.11 extra time, large swarms 1.13 -> 1.05, 0
collisions and 100 % success on both links; told 1 m, a circle of 16 deadlocked once on the
degraded link."""

TOLD_SHARE_KEY = "filtered_told_share"
"""The weights config's entry (docs/POLICY_SPEC.md): the share of the separation flight tells
these weights with the filter on, the geometry they were trained in (`covey train
--filtered-told-share`)."""


def config_told_share(config: dict, where: str = "weights") -> float:
    """The told share a weights config states (LEGACY_FILTERED_TOLD_SHARE when it states none);
    one that is not a number in (0, 4] is refused with the reason."""
    share = config.get(TOLD_SHARE_KEY, LEGACY_FILTERED_TOLD_SHARE)
    if isinstance(share, bool) or not isinstance(share, (int, float)):
        raise ValueError(f"{where}: {TOLD_SHARE_KEY} must be a number, got {share!r}")
    if not (math.isfinite(share) and 0.0 < share <= 4.0):
        raise ValueError(f"{where}: {TOLD_SHARE_KEY} must be in (0, 4], got {share}")
    return float(share)


def read_weights(path: str | Path | None) -> tuple[Path, dict[str, np.ndarray], dict]:
    """(path, checked arrays, config) of a weights file (None: the shipped ones); a missing
    file, bad arrays or a config that is not a JSON object are refused with the reason."""
    path = Path(path) if path is not None else DEFAULT_WEIGHTS
    if not path.is_file():
        raise FileNotFoundError(f"no policy weights at {path}")
    arrays = load_weight_arrays(path)
    config = parse_json(str(arrays["config"]), f"{path} 'config'")
    if not isinstance(config, dict):
        raise ValueError(f"{path}: 'config' is not a JSON object")
    return path, arrays, config


@functools.lru_cache(maxsize=8)
def filtered_told_share(path: str | Path | None = None) -> float:
    """The share of the separation flight tells the weights at `path` (None: the shipped ones)
    with the filter on: their config's `filtered_told_share`, else LEGACY_FILTERED_TOLD_SHARE."""
    path, _, config = read_weights(path)
    return config_told_share(config, str(path))


FILTERED_BERTH_SHARE = filtered_told_share(None)
"""With the separation filter on, flight tells the shipped weights this share of the separation,
unless told otherwise (their config's `filtered_told_share`: docs/policy.md, "Trained on
drifting estimates")."""

TOLD_SIGMA_FREE_M = 0.5
"""The position 1-sigma up to which the policy is told the separation as above, whatever the
filter's inflation: the realistic preset's GNSS, where FILTERED_BERTH_SHARE and sigma_k were
chosen. Beyond it the filter keeps a berth the network was never told (7.8 m between estimates
at 1 m), and dense crowds jammed: the network's distance scale then grows with the inflation of
the excess (`told_scale`; docs/sky.md, "GNSS worse than the preset")."""


def told_scale(separation_m, sigma_k, free_m, pos_sigma_m, nbr_sigma_max_m):
    """How many times the told separation the network is told now (>= 1; scalars or arrays
    alike): 1 + sigma_k hypot(x_own, x_nbr) / separation_m, x = max(0, sigma - free_m), with
    the own 1-sigma and the largest cooperative neighbour's (traffic's own accuracy, an ADS-B
    report's tens of metres, does not rescale the fleet's view); free_m None: 1 (off, a told separation asked
    explicitly). NaN sigmas count as 0 here (the filter refuses them). firmware/
    covey_guidance.c covey_told_scale is its C twin (parity tested)."""
    if free_m is None:
        return np.ones_like(np.asarray(pos_sigma_m, float))[()]
    excess = np.hypot(
        np.fmax(np.asarray(pos_sigma_m, float) - free_m, 0.0),
        np.fmax(np.asarray(nbr_sigma_max_m, float) - free_m, 0.0),
    )
    return (1.0 + sigma_k * excess / separation_m)[()]


def told_separation_m(
    separation_m: float,
    safety_filter: bool,
    policy_separation_m: float | None = None,
    inflation_m: float = 0.0,
    share: float | None = None,
) -> float:
    """The separation flight tells the policy (its distance scale): `policy_separation_m` when
    given; else `share` (None: FILTERED_BERTH_SHARE, the shipped weights'; other weights:
    `filtered_told_share(path)`) x (separation_m + inflation_m) with the filter on, and
    separation_m + inflation_m without it (alone, the policy keeps the separation itself).
    The filter always keeps separation_m, plus its uncertainty inflation per pair
    (policy.safety.pair_radius_m); `inflation_m` tells the policy a typical one (0: none).
    One rule for the agents, fleet-sim, `covey eval` and the emulator's onboard C mode;
    firmware/covey_guidance.c covey_told_separation_m is its C twin (parity tested)."""
    if policy_separation_m is not None:
        return float(policy_separation_m)
    told = float(separation_m) + float(inflation_m)
    if not safety_filter:
        return told
    return told * (FILTERED_BERTH_SHARE if share is None else share)


class GuidancePolicy:
    """The trained guidance policy with world-unit scaling and an optional safety filter."""

    def __init__(
        self,
        net: Network,
        obs_cfg: ObsConfig,
        config: dict,
        separation_m: float = 3.0,
        cruise_speed_m_s: float = 1.0,
        safety_filter: bool = True,
        max_neighbours: int | None = None,
        safety_cfg: safety.SafetyConfig | None = None,
        policy_separation_m: float | None = None,
        sparse_rule: sparse.SparseConfig | bool | None = True,
        keep_out_m=None,
        fence_m=None,
        told_sigma_free_m: float | None = TOLD_SIGMA_FREE_M,
    ):
        """The defaults fly as the agents do (agent.guidance.GuidanceConfig).

        `told_sigma_free_m`: beyond this position 1-sigma (own or a neighbour's) the network's
        distance scale grows with the filter's inflation of the excess (`told_scale`); None:
        never (the told separation stays as given, e.g. one that already counts it).

        `keep_out_m` [(K, 2) polygon vertices, local north/east metres] and `fence_m` (K, 2):
        see `set_zones`; None: no zones (today's behaviour).

        `policy_separation_m`: the separation the network is told, i.e. its distance scale (3
        policy units = this many metres). None: as flight tells it, `told_separation_m` (the
        weights' told share of the separation with the filter on, the whole separation without it). Smaller
        than separation_m makes the policy keep a narrower berth while the filter still keeps
        separation_m (docs/policy.md, "The policy's berth"). The decision period stays
        separation_m's.

        `sparse_rule`: in sparse traffic, command the straight line at the goal instead of the
        policy's velocity (policy.sparse), for flight that filters every command, which then
        resolves the encounter. True: SparseConfig() with the filter on, off without it; a
        SparseConfig: these thresholds, also without this policy's filter (for a caller that
        filters every tick itself, as the agents do); False or None: the policy always."""
        if not (np.isfinite(separation_m) and separation_m > 0):
            raise ValueError(f"separation_m must be finite and > 0, got {separation_m}")
        if not (np.isfinite(cruise_speed_m_s) and cruise_speed_m_s > 0):
            raise ValueError(f"cruise_speed_m_s must be finite and > 0, got {cruise_speed_m_s}")
        if max_neighbours is not None and max_neighbours < 0:
            raise ValueError(f"max_neighbours must be >= 0 or None, got {max_neighbours}")
        self.net = net
        self.obs_cfg = obs_cfg
        self.config = config
        policy_separation_m = told_separation_m(
            separation_m,
            safety_filter,
            policy_separation_m,
            share=config_told_share(config),
        )
        if not (np.isfinite(policy_separation_m) and policy_separation_m > 0):
            raise ValueError(
                f"policy_separation_m must be finite and > 0, got {policy_separation_m}"
            )
        self.dist_scale_m = policy_separation_m / 3.0
        """World metres per policy unit of distance (what the network sees)."""
        self.separation_m = float(separation_m)
        """The separation the filter keeps."""
        self.cruise_speed_m_s = cruise_speed_m_s
        self.max_neighbours = max_neighbours
        self.safety_filter = safety_filter
        if sparse_rule is None or isinstance(sparse_rule, (bool, np.bool_)):
            sparse_rule = sparse.SparseConfig() if sparse_rule and safety_filter else None
        elif not isinstance(sparse_rule, sparse.SparseConfig):
            raise TypeError(
                f"sparse_rule must be a SparseConfig, True, False or None, got {sparse_rule!r}"
            )
        self.sparse_rule: sparse.SparseConfig | None = sparse_rule
        """The rule's thresholds, None when it is off."""
        base = safety_cfg or safety.SafetyConfig()
        self.safety_cfg = replace(base, radius_m=separation_m, max_speed_m_s=cruise_speed_m_s)
        self.actor = Actor(net, obs_cfg, self.dist_scale_m, max_neighbours)
        """The network on observations (policy.actor): the action before it is flown."""
        if told_sigma_free_m is not None and not (
            np.isfinite(told_sigma_free_m) and told_sigma_free_m >= 0
        ):
            raise ValueError(
                f"told_sigma_free_m must be finite and >= 0 or None, got {told_sigma_free_m}"
            )
        self.told_sigma_free_m = told_sigma_free_m
        self.zones: ZoneSet | None = None
        """Keep-out edges the filter keeps clear of (policy.zone_lines), None: none."""
        self.router = None
        """The route planner around them (policy.routes.Router), None: none."""
        if keep_out_m is not None or fence_m is not None:
            self.set_zones(keep_out_m or (), fence_m)

    def set_zones(self, keep_out_m, fence_m=None) -> None:
        """Keep out of these polygons [(K, 2) north/east metres] (and inside the fence):
        `command` and `preferred` fly towards the route planner's next waypoint instead of the
        goal (policy.routes: around the zones inflated by the filter's zone radius plus a
        margin), and the filter (when on) keeps ZONE_CLEARANCE_SHARE x the padded separation
        from every zone edge as a hard constraint (policy.zone_lines). Empty: no zones. A bad
        polygon is a ValueError naming it."""
        from policy.routes import zones_for  # shapely and scipy: only with zones

        self.zones, self.router = zones_for(self.safety_cfg, keep_out_m, fence_m)

    def _waypoint(self, pos_m, goal_m, pos_sigma_m: float = 0.0):
        """Where to fly now for `goal_m` (2,): the route's next waypoint with zones, on routes
        that keep the filter's padding for pos_sigma_m (sigma_k x it) more from them, else
        the goal. Inputs that are not two finite numbers come back as they are (the checked
        path names them)."""
        if self.router is None:
            return goal_m
        try:
            pad = self.safety_cfg.sigma_k * float(pos_sigma_m)
            return self.router.next_waypoint(pos_m, goal_m, pad)
        except (TypeError, ValueError):
            return goal_m

    def _waypoints(self, pos_m, goal_m, pos_sigma_m=None) -> np.ndarray:
        """`waypoint` of N rows (N, 2), pos_sigma_m (N,) or None (0)."""
        if self.router is None:
            return goal_m
        pad = None if pos_sigma_m is None else self.safety_cfg.sigma_k * np.asarray(pos_sigma_m)
        return self.router.next_waypoints(pos_m, goal_m, pad)

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        separation_m: float = 3.0,
        cruise_speed_m_s: float = 1.0,
        safety_filter: bool = True,
        max_neighbours: int | None = None,
        safety_cfg: safety.SafetyConfig | None = None,
        policy_separation_m: float | None = None,
        sparse_rule: sparse.SparseConfig | bool | None = True,
        keep_out_m=None,
        fence_m=None,
        told_sigma_free_m: float | None = TOLD_SIGMA_FREE_M,
    ) -> GuidancePolicy:
        """Loads a weights file (docs/POLICY_SPEC.md); None = the shipped weights. The other
        arguments are the constructor's: the defaults fly as the agents do."""
        path, arrays, config = read_weights(path)
        if config.get("encoder", "lstm") != "lstm":
            raise ValueError(
                f"{path}: the runtime only runs encoder 'lstm', not {config['encoder']!r}"
            )
        try:
            obs_cfg = ObsConfig.from_dict(config)
            net = Network.from_arrays(arrays)
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise ValueError(f"{path}: not usable weights ({' '.join(str(exc).split())})") from None
        if net.w_ih.shape[1] != obs_cfg.input_size:
            raise ValueError(
                f"{path}: LSTM input {net.w_ih.shape[1]} does not fit encoding {obs_cfg.encoding}"
            )
        return cls(
            net,
            obs_cfg,
            config,
            separation_m,
            cruise_speed_m_s,
            safety_filter,
            max_neighbours,
            safety_cfg,
            policy_separation_m,
            sparse_rule,
            keep_out_m,
            fence_m,
            told_sigma_free_m,
        )

    @property
    def decision_period_s(self) -> float:
        """World time of one training step (1 s in policy units): call `preferred` at this
        period and hold it in between, running `filter` on it at the control rate (as the
        agents do); or call `command` at the control rate."""
        return float(self.config.get("dt_s", 1.0)) * self.separation_m / 3.0 / self.cruise_speed_m_s

    # --- the ways in: command, preferred, filter, command_batch ---------------------

    def filter(
        self,
        pos_m,
        vel_m_s,
        pref_vel_m_s,
        nbr_pos_m,
        nbr_vel_m_s,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ):
        """The safety filter alone (world units): pref_vel_m_s changed as little as possible.
        Uncertainties, cooperative and manned flags as `command` takes them."""
        pos_m = check_array("pos_m", pos_m, (2,))
        nbr_pos_m = check_array("nbr_pos_m", nbr_pos_m, (-1, 2))
        k = nbr_pos_m.shape[0]
        sky = Sky.checked(pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, k, nbr_manned)
        return safety.filter_velocity(
            pos_m,
            check_array("vel_m_s", vel_m_s, (2,)),
            check_array("pref_vel_m_s", pref_vel_m_s, (2,)),
            nbr_pos_m,
            check_array("nbr_vel_m_s", nbr_vel_m_s, (k, 2)),
            self.safety_cfg,
            **sky.kwargs(),
            zones=self.zones,
        )

    def command(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> np.ndarray:
        """Velocity command (2,) in m/s (north, east) for one vehicle.

        Real vehicles: `pos_sigma_m` is the own position estimate's 1-sigma (metres, per axis;
        PX4's eph), `nbr_pos_sigma_m` (K,) the neighbours' as they reported them, and
        `nbr_cooperative` (K,) bool False for a neighbour that does not avoid (traffic): the
        filter keeps each pair apart by separation_m (1 + margin) + sigma_k sqrt(si^2 + sj^2)
        and takes the whole correction against traffic (policy.safety.pair_radius_m);
        `nbr_manned` (K,) bool True for a manned aircraft (ADS-B's manned emitter categories):
        traffic kept `manned_radius_m` from (30 m before margin and uncertainty). The defaults
        (0, None, None, None) fly as before.

        The inputs become one Observation (Observation.checked: a ValueError names a bad one;
        float64 arrays of the right shapes pass uncopied).

        Called every tick, this is all a caller needs. For the decision hold (as the agents
        fly), hold `preferred` instead and `filter` it every tick: a held `command` keeps the
        filter's answer to the moment it decided, on top of the filter's answer to now."""
        sky = Sky.checked(pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned=nbr_manned)
        obs = Observation.checked(
            pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, sky
        )
        return self._command(obs, filtered=True)

    def preferred(
        self,
        pos_m,
        vel_m_s,
        heading_rad,
        goal_m,
        nbr_pos_m,
        nbr_vel_m_s,
        nbr_heading_rad,
        pos_sigma_m: float = 0.0,
        nbr_pos_sigma_m=None,
        nbr_cooperative=None,
        nbr_manned=None,
    ) -> np.ndarray:
        """The velocity (2,) to hold for one decision period, as the agents do: the policy's,
        or the sparse rule's straight line, not yet filtered. Every tick, fly
        `filter(pos_m, vel_m_s, held, nbr_pos_m, nbr_vel_m_s)`; at the decision that is
        `command`. Same inputs and checks as `command`."""
        sky = Sky.checked(pos_sigma_m, nbr_pos_sigma_m, nbr_cooperative, nbr_manned=nbr_manned)
        obs = Observation.checked(
            pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, sky
        )
        return self._command(obs, filtered=False)

    def command_batch(self, obs: Observations | Swarm) -> np.ndarray:
        """Velocity commands (N, 2) in m/s of N vehicles, float32 network (like torch).

        Observations: each vehicle with its own padded view of the others (what its link
        delivered; unchecked, for simulations and the agents' views). Swarm: every active
        vehicle sees every other active one; inactive ones get (0, 0) and are invisible
        (Swarm.checked names a bad input)."""
        if isinstance(obs, Swarm):
            return self._command_swarm(obs)
        if not isinstance(obs, Observations):
            raise TypeError(f"command_batch takes Observations or a Swarm, got {type(obs)}")
        obs = replace(obs, goal_m=self._waypoints(obs.pos_m, obs.goal_m, obs.pos_sigma_m))
        a, _ = self.actor.action_batch(self._told_batch(obs))
        v = features.action_to_velocity(a, obs.heading_rad) * self.cruise_speed_m_s
        views = (obs.pos_m, obs.vel_m_s)
        nbrs = (obs.nbr_pos_m, obs.nbr_vel_m_s, obs.nbr_valid)
        if self.sparse_rule is not None:
            v, _ = self._sparse(*views, obs.goal_m, v, *nbrs, **obs.sky())
        if self.safety_filter:
            v = safety.filter_padded(
                *views, v, *nbrs, self.safety_cfg, **obs.sky(), zones=self.zones
            )
        return v

    # --- inside: one observation ------------------------------------------------------

    def _command(self, obs: Observation, filtered: bool) -> np.ndarray:
        """The action of `obs` (towards the route's waypoint with zones) as a velocity."""
        if self.router is not None:
            obs = obs.with_goal(self._waypoint(obs.pos_m, obs.goal_m, obs.sky.pos_sigma_m))
        return self._velocity(self.actor.pair(self._told(obs)), obs, filtered)

    def _told(self, obs: Observation) -> Observation:
        """What the network sees of `obs`: zoomed out by `told_scale` where the sigmas are
        beyond told_sigma_free_m (the sparse rule and the filter see `obs` as it is)."""
        sky = obs.sky
        if self.told_sigma_free_m is None or sky is EXACT:
            return obs
        return obs.zoomed(1.0 / float(self._told_scale(sky.pos_sigma_m, sky.nbr_sigma_max_m())))

    def _told_batch(self, obs: Observations) -> Observations:
        """`_told` row by row."""
        if self.told_sigma_free_m is None or obs.pos_sigma_m is None:
            return obs
        scale = self._told_scale(obs.pos_sigma_m, obs.nbr_sigma_max_m())
        return obs.zoomed(1.0 / np.asarray(scale, float).reshape(-1))

    def _told_scale(self, pos_sigma_m, nbr_sigma_max_m):
        """`told_scale` with this policy's separation, sigma_k and told_sigma_free_m."""
        return told_scale(
            self.separation_m,
            self.safety_cfg.sigma_k,
            self.told_sigma_free_m,
            pos_sigma_m,
            nbr_sigma_max_m,
        )

    def _velocity(self, a: tuple, obs: Observation, filtered: bool = True) -> np.ndarray:
        """Body (fwd, right) action a -> (north, east) velocity times the cruise speed, then
        the sparse rule (when on), then the filter (when on, `filtered`, and there are
        neighbours or zones)."""
        heading = obs.heading_rad
        c, sn, u = math.cos(heading), math.sin(heading), self.cruise_speed_m_s
        a0, a1 = a
        v = np.array(((a0 * c - a1 * sn) * u, (a0 * sn + a1 * c) * u))
        sky = {} if obs.sky is EXACT else obs.sky.kwargs()
        if self.sparse_rule is not None:
            v, _ = sparse.choose_one(
                obs.pos_m,
                obs.vel_m_s,
                obs.goal_m,
                v,
                obs.nbr_pos_m,
                obs.nbr_vel_m_s,
                self.safety_cfg,
                self.sparse_rule,
                self.decision_period_s,
                **sky,
            )
        if filtered and self.safety_filter and (obs.nbr_pos_m.shape[0] or self.zones is not None):
            v = safety.filter_one(
                obs.pos_m,
                obs.vel_m_s,
                v,
                obs.nbr_pos_m,
                obs.nbr_vel_m_s,
                self.safety_cfg,
                **sky,
                zones=self.zones,
            )
        return v

    def _sparse(self, pos_m, vel_m_s, goal_m, v, nbr_pos_m, nbr_vel_m_s, nbr_valid, **sky):
        """policy.sparse.choose_padded with this policy's filter and decision period (`sky`:
        its uncertainties and cooperative flags)."""
        return sparse.choose_padded(
            pos_m,
            vel_m_s,
            goal_m,
            v,
            nbr_pos_m,
            nbr_vel_m_s,
            nbr_valid,
            self.safety_cfg,
            self.sparse_rule,
            self.decision_period_s,
            **sky,
        )

    def _command_swarm(self, swarm: Swarm) -> np.ndarray:
        """command_batch of a Swarm: the network's neighbours come from the positions
        (features.observe_batch); the sparse rule sees every active vehicle (encounters reach
        past the network's sense range)."""
        n, active = swarm.pos_m.shape[0], swarm.active
        pos_m, vel_m_s = swarm.pos_m, swarm.vel_m_s
        swarm = replace(swarm, goal_m=self._waypoints(pos_m, swarm.goal_m))
        a, nbr = self.actor.action_batch(swarm)
        v = features.action_to_velocity(a, swarm.heading_rad) * self.cruise_speed_m_s
        if self.sparse_rule is not None:
            others = active[None, :] & ~np.eye(n, dtype=bool)
            every_pos, every_vel = (np.broadcast_to(x, (n, n, 2)) for x in (pos_m, vel_m_s))
            v, _ = self._sparse(pos_m, vel_m_s, swarm.goal_m, v, every_pos, every_vel, others)
        if self.safety_filter:
            v = safety.filter_batch(pos_m, vel_m_s, v, nbr, self.safety_cfg, zones=self.zones)
        v[~active] = 0.0
        return v
