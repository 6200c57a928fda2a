"""`covey eval --suites zones`: scenes with keep-out zones, flown as the agents fly them.

Every controller flies routed gotos (policy.routes: the goal replaced by the next waypoint, as
agent/guidance.py does); the filtered ones (policy+filter, orca, c+filter) also keep the zone
edges as hard lines (policy.zone_lines; c+filter through the C core, covey_safety_filter_zones,
applied to the C guidance tick's output). The unfiltered ones (policy, straight) show what the
routes alone do. Counted on the true positions (the recorded tracks):
- `zone_entries`: vehicles that came within ZONE_ENTRY_SHARE x the separation (1.5 m at 3 m)
  of a zone, inside it included;
- `min_zone_m`: the closest any vehicle came to a zone;
- `refused`: gotos refused as the flight core refuses them: a goal nearer a zone than the
  filter's clearance (1.8 m + sigma_k x the position 1-sigma) whose nearest point outside it
  lies beyond the arrival radius (policy.routes `Router.check_goal`); the others fly to that
  point, and the refused ones are left out of the scene;
- `route_time`: mean arrival time over the route's length at cruise speed (1.0 = flying the
  planned route at full speed; `extra_time` stays relative to the straight line).
"""

from __future__ import annotations

import numpy as np

from policy import evalsim
from policy.zone_lines import ZONE_ENTRY_SHARE

ZONE_FILTER = {"policy+filter": "numpy", "orca": "numpy", "c+filter": "c"}
"""Controllers that keep the zone edges in their filter, and which filter does it. A controller
with `set_zones` (agent/eval_agents.py: the agents' own guidance) is given the zones and routes
and filters itself."""


class Routed:
    """A controller flying routed gotos, its output through the zone filter (`ZONE_FILTER`)."""

    def __init__(self, inner, router, zones, safety_cfg, kind: str | None, czones=None, lanes=None):
        self.inner, self.router, self.zones = inner, router, zones
        self.safety_cfg, self.kind, self.czones = safety_cfg, kind, czones
        self.lanes = lanes
        """policy.lanes.LaneConfig: who waits at a one-lane gap (None: the default)."""
        for attr in ("uses_sigma", "uses_cooperative"):
            if getattr(inner, attr, False):
                setattr(self, attr, True)

    def reset(self) -> None:
        if hasattr(self.inner, "reset"):
            self.inner.reset()

    def __call__(
        self, ids, t_s, pos, vel, heading, goal, nbr_pos, nbr_vel, nbr_heading, valid, **kw
    ):
        from policy.lanes import hold_short
        from policy.safety import filter_padded

        way = goal
        if self.router is not None:  # routes widened by the filter's padding, as the agents'
            sig = kw.get("pos_sigma_m")
            pad = None if sig is None else self.safety_cfg.sigma_k * np.asarray(sig, float)
            way = self.router.next_waypoints(pos, goal, pad)
            coop = kw.get("nbr_cooperative")
            mates = valid if coop is None else valid & coop
            n = valid.shape[1]  # neighbour columns are vehicle numbers, as `ids` are
            way = hold_short(
                self.router,
                pos,
                goal,
                way,
                pad,
                nbr_pos,
                nbr_vel,
                mates,
                ids,
                np.broadcast_to(np.arange(n), valid.shape),
                self.lanes,
            )
        v = self.inner(ids, t_s, pos, vel, heading, way, nbr_pos, nbr_vel, nbr_heading, valid, **kw)
        if self.kind == "numpy":
            sky = {
                k: kw[k] for k in ("pos_sigma_m", "nbr_pos_sigma_m", "nbr_cooperative") if k in kw
            }
            v = filter_padded(
                pos, vel, v, nbr_pos, nbr_vel, valid, self.safety_cfg, **sky, zones=self.zones
            )
        elif self.kind == "c":
            out = np.zeros_like(v)
            sig, nsig, coop = (
                kw.get(k) for k in ("pos_sigma_m", "nbr_pos_sigma_m", "nbr_cooperative")
            )
            for i in range(len(pos)):
                m = valid[i]
                r = self.czones.evaluate(
                    self.safety_cfg,
                    pos[i],
                    vel[i],
                    v[i],
                    nbr_pos[i, m],
                    nbr_vel[i, m],
                    pos_sigma_m=0.0 if sig is None else float(sig[i]),
                    nbr_pos_sigma_m=None if nsig is None else nsig[i, m],
                    nbr_cooperative=None if coop is None else coop[i, m],
                )
                if r.status != "ok":
                    raise RuntimeError(f"C zone filter fault: {r.status}")
                out[i] = r.vel_m_s
            v = out
        return v


def _nobody_flew(refused: int) -> dict:
    """The metrics of a scene whose every goto was refused, as the flight core refuses them: no
    flight, nothing arrived, nothing entered, no distances."""
    return {
        "n": 0,
        "success": False,
        "arrived": 0,
        "collisions": 0,
        "timeouts": 0,
        "min_sep": None,
        "est_collisions": 0,
        "est_min_sep": None,
        "intruder_min_sep": None,
        "manned_min_sep": None,
        "manned_entries": 0,
        "intruder_heard_s": None,
        "extra_time": None,
        "path_ratio": None,
        "mean_acc": None,
        "steps": 0,
        "refused": refused,
        "zone_entries": 0,
        "min_zone_m": None,
        "route_time": None,
        "tracks": np.zeros((0, 0, 2)),
        "goals": np.zeros((0, 2)),
    }


def run(
    name, starts, goals, zones_m, controller, link, sim_cfg, rng, aware=True, lanes=None, **options
):
    """One zone scene with one controller: evalsim.run's metrics plus the zone counts (module
    docstring); the tracks stay in the result (`tracks`, `goals`) for figures. The filter's
    config is the controller's own (Held.safety_cfg, orca's, CPolicy's), else the default.
    `aware` False: the controller as it is, told nothing of the zones (the "before" numbers).
    `lanes`: policy.lanes.LaneConfig (None: the default, as the agents fly)."""
    import dataclasses

    import shapely

    from policy.routes import zones_for
    from policy.safety import SafetyConfig

    safety_cfg = (
        getattr(controller, "safety_cfg", None)
        or getattr(getattr(controller, "policy", None), "safety_cfg", None)
        or SafetyConfig(dt_s=sim_cfg.dt_s)
    )

    zones, router = zones_for(safety_cfg, zones_m)
    kind = ZONE_FILTER.get(name) if aware else None
    czones = None
    if kind == "c":
        # The C controller brings its own zone filter (firmware/ceval.py): policy/ never imports
        # firmware/, which sits above it.
        czones = controller.zone_filter(zones_m, zones.radius_m, zones.time_horizon_s)
    if aware and hasattr(controller, "set_zones"):  # it routes and keeps the edges itself
        controller.set_zones(zones_m)
        routed = controller
    else:
        routed = Routed(
            controller, router if aware else None, zones, safety_cfg, kind, czones, lanes
        )
    refused = np.zeros(len(goals), bool)
    if aware:  # as the flight core takes a goto (agent/flight_core.py `_clear_goal`)
        pad_m = safety_cfg.sigma_k * sim_cfg.vehicles.pos_sigma_m
        checks = [router.check_goal(g, pad_m) for g in np.asarray(goals, float)]
        refused = np.array([bool(c.problem(sim_cfg.arrive_m)) for c in checks])
        goals = np.array([c.goal_m for c in checks])[~refused]
        starts = np.asarray(starts, float)[~refused]
        options = {k: np.asarray(v)[~refused] for k, v in options.items()}
        if refused.all():  # every goal refused (a wide clearance at a poor sigma): none flies
            return _nobody_flew(int(refused.sum()))
    r = evalsim.run(
        starts, goals, routed, link, dataclasses.replace(sim_cfg, record=True), rng, **options
    )
    r["refused"] = int(refused.sum())
    tracks = r["tracks"]
    union = shapely.union_all([shapely.Polygon(z) for z in zones_m])
    flat = tracks.reshape(-1, 2)
    seen = np.isfinite(flat).all(axis=1)
    dist = np.full(len(flat), np.inf)
    dist[seen] = shapely.distance(shapely.points(flat[seen]), union)
    dist = dist.reshape(tracks.shape[:2])
    entry_m = ZONE_ENTRY_SHARE * sim_cfg.collide_m
    closest = dist.min(axis=0)
    # arrival time per vehicle: the last step it flew (vehicles leave on arrival)
    flew = np.isfinite(tracks[..., 0])
    last = np.where(flew.any(axis=0), flew.shape[0] - 1 - np.argmax(flew[::-1], axis=0), 0)
    route_len = np.array(
        [router.plan(s, g).length_m for s, g in zip(starts, goals, strict=True)], float
    )
    arrived_at = last * sim_cfg.dt_s
    done = np.hypot(*(tracks[last, np.arange(len(starts))] - goals).T) <= sim_cfg.arrive_m + 0.2
    ok = done & np.isfinite(route_len)
    r["zone_entries"] = int((closest < entry_m).sum())
    r["min_zone_m"] = float(closest.min())
    r["route_time"] = (
        float(np.mean(arrived_at[ok] * sim_cfg.speed / route_len[ok])) if ok.any() else None
    )
    r["goals"] = goals
    return r


def plot_scenes(flown: list, png) -> None:
    """A row of panels, one flown scene each: [(title, tracks (T, N, 2), goals (N, 2), zones)];
    zones filled, the route inflation dashed, east to the right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import shapely

    from policy.routes import RouteConfig

    fig, axes = plt.subplots(1, len(flown), figsize=(4.2 * len(flown), 4.4))
    axes = np.atleast_1d(axes)
    cmap = plt.get_cmap("tab10")
    infl = RouteConfig().inflate_m
    for ax, (title, tracks, goals, zones) in zip(axes, flown, strict=True):
        for z in zones:
            zz = np.vstack([z, z[:1]])
            ax.fill(zz[:, 1], zz[:, 0], color="0.75", zorder=1)
            grown = shapely.Polygon(z).buffer(infl, join_style="mitre", mitre_limit=2.0)
            g = np.asarray(grown.exterior.coords)
            ax.plot(g[:, 1], g[:, 0], "--", lw=0.6, color="0.4", zorder=1)
        for i in range(tracks.shape[1]):
            c = cmap(i % 10)
            ax.plot(tracks[:, i, 1], tracks[:, i, 0], lw=1.0, color=c, zorder=2)
            ax.plot(tracks[0, i, 1], tracks[0, i, 0], "o", ms=3, color=c, zorder=3)
            ax.plot(goals[i, 1], goals[i, 0], "x", ms=5, color=c, zorder=3)
        ax.set_aspect("equal")
        ax.set_xlabel("east (m)")
        ax.set_title(title, fontsize=9)
    axes[0].set_ylabel("north (m)")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
