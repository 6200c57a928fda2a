"""Intruders heard late: how much warning the fleet needs. One covey vehicle flies a 1 m/s goto;
an intruder that does not cooperate (1x, 1.5x, 2x its speed) appears on the link `warn_s`
before the two would come within 3 m if nobody acted: head-on on the vehicle's line, 1 m
aside of it, crossing at right angles, and (faster ones) overtaking from behind. Issue 35's
target: 0 collisions wherever the intruder is heard at least 2 s before the conflict.

    python -m bench.late_intruder [--quick]   # bench/results/late_intruder.json

Both are already flying their lines at their speeds when the intruder appears (evalsim's
`flying_start`). It broadcasts from t = 0 (the moment it appears); on the 3 Hz lossy link the first
state reaches the vehicle up to a period plus 100 ms later, or later still after losses, so
`warn_s` there is the warning at best. Collisions and the closest approach are on true
positions; ideal and realistic vehicles; policy+filter, c+filter (the C core) and agents (the
agents' own guidance tick).
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from bench import common

WARN_S = (2.0, 3.0, 5.0)
RATIOS = (1.0, 1.5, 2.0)
SCENES = ("head-on", "aside-1m", "crossing", "overtake")
CONTROLLERS = ("policy+filter", "c+filter", "agents")
SEEDS = range(5)
"""Link-loss and vehicle-noise draws per setting."""


def scene(name: str, ratio: float, warn_s: float):
    """(starts, goals, non_cooperative, speeds): the vehicle bound east through the origin,
    the intruder placed so that, flying straight, they would come within 3 m `warn_s` after
    the start; None where the scene does not exist (overtaking at 1x)."""
    if name == "overtake" and ratio <= 1.0:
        return None
    own_v = np.array([0.0, 1.0])
    if name == "crossing":
        u = np.array([1.0, 0.0])  # northbound across the vehicle's path
        aside = np.zeros(2)
    else:
        u = np.array([0.0, 1.0 if name == "overtake" else -1.0])
        aside = np.array([1.0, 0.0]) if name == "aside-1m" else np.zeros(2)
    v_i = u * ratio
    rel = v_i - own_v
    # they pass the origin (the intruder `aside` of it) at t_meet; the distance at time t is
    # |aside + rel (t - t_meet)|: first within 3 m at t_meet - sqrt(9 - |aside|^2) / |rel|
    t_sep = math.sqrt(9.0 - float(aside @ aside)) / float(np.hypot(*rel))
    t_meet = warn_s + t_sep
    start_own = -own_v * t_meet
    start_i = aside - v_i * t_meet
    far = 30.0
    starts = np.array([start_own, start_i])
    goals = np.array([own_v * far, aside + u * far * ratio])
    return starts, goals, np.array([False, True]), np.array([1.0, ratio])


def main(quick: bool = False) -> dict:
    import policy.eval as ev
    from agent.eval_agents import CONTROLLERS as EXTRA
    from policy import evalsim
    from policy.pointmass import VehicleModel
    from policy.tracking import TrackingConfig

    seeds = range(2) if quick else SEEDS
    rows = []
    for vehicles in ("ideal", "realistic"):
        model = VehicleModel.named(vehicles)
        cfg = ev.EvalConfig(vehicles=vehicles, controllers=CONTROLLERS, progress=False)
        ctrls = ev.controllers(cfg, EXTRA)
        sim = evalsim.EvalSimConfig(vehicles=model, tracking=TrackingConfig.assumed(model, True))
        for link_name, link in (("perfect", evalsim.PERFECT), ("degraded", evalsim.DEGRADED)):
            for warn_s in WARN_S:
                for ratio in RATIOS:
                    for name in SCENES:
                        built = scene(name, ratio, warn_s)
                        if built is None:
                            continue
                        starts, goals, nc, speeds = built
                        for c in CONTROLLERS:
                            closest = []
                            for seed in seeds:
                                ctrls[c].reset() if hasattr(ctrls[c], "reset") else None
                                rng = np.random.default_rng([35, seed])
                                r = evalsim.run(
                                    starts,
                                    goals,
                                    ctrls[c],
                                    link,
                                    sim,
                                    rng,
                                    nc,
                                    speeds,
                                    flying_start=True,
                                )
                                closest.append(r["intruder_min_sep"])
                            rows.append(
                                {
                                    "vehicles": vehicles,
                                    "link": link_name,
                                    "warn_s": warn_s,
                                    "ratio": ratio,
                                    "scene": name,
                                    "controller": c,
                                    "runs": len(closest),
                                    "collisions": sum(d < 3.0 for d in closest),
                                    "closest_m": min(closest),
                                }
                            )
            common.say(f"{vehicles}, {link_name}: done")
    summary: dict = {}
    for r in rows:
        key = f"{r['vehicles']}/{r['link']}/{r['warn_s']:g}s"
        s = summary.setdefault(key, {"runs": 0, "collisions": 0, "closest_m": math.inf})
        s["runs"] += r["runs"]
        s["collisions"] += r["collisions"]
        s["closest_m"] = min(s["closest_m"], r["closest_m"])
    result = {"quick": quick, "summary": summary, "rows": rows}
    common.write_json("late_intruder", result)
    return result


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    res = main(ap.parse_args().quick)
    for key, s in res["summary"].items():
        print(f"{key:28s} {s['collisions']}/{s['runs']} under 3 m, closest {s['closest_m']:.2f} m")
    for r in res["rows"]:
        if r["collisions"]:
            print(
                f"  {r['vehicles']} {r['link']} warn {r['warn_s']:g} s {r['ratio']:g}x "
                f"{r['scene']} {r['controller']}: {r['collisions']}/{r['runs']}, "
                f"closest {r['closest_m']:.2f} m"
            )
