"""One vehicle's decision and separation filter through the compiled C core (firmware/).

An agent flies one vehicle: its guidance runs `BatchGuidance`'s single-vehicle fast paths every
tick, the filter on the held velocity and, once per decision period, the policy. `CCore` runs
those two calls in the C core instead (covey_policy.c with the sparse rule, covey_safety.c),
which equals numpy's to float32 precision (tests/test_guidance_c.py against the numpy paths,
the reference; firmware's own parity tests for every rule) in a fraction of the time
(docs/companion.md, "Round nine"). Where the C core does not cover a call, numpy answers it:
keep-out zones or a fence (the numpy filter keeps their edges), more neighbours than the core
takes, or a fault the core reports. The library is built on first use with the system C
compiler into firmware/build/ (cached by a hash of its sources); without a compiler the agent
says so once and flies numpy.
"""

from __future__ import annotations

import logging
import subprocess

import numpy as np

from policy import safety

log = logging.getLogger(__name__)

UNAVAILABLE = (
    "the C guidance core is not available (%s): guidance runs in numpy, a little slower "
    "(install a C compiler, e.g. apt install gcc, or pass --no-c-core to say so)"
)


def build(policy_path: str | None = None) -> bool:
    """Build the C core's library for these weights now (None: the shipped ones), so that the
    agents a launcher starts next load it instead of each compiling it (`covey demo`); False
    (logged) where it cannot be built: the agents will fly numpy."""
    from firmware.cpolicy import load_library

    try:
        load_library(policy_path)
    except (OSError, subprocess.CalledProcessError) as exc:
        log.warning(UNAVAILABLE, exc)
        return False
    return True


class CCore:
    """The C twin of one row's `_decide` (GuidancePolicy.command, unfiltered) and `_filter`
    (policy.safety.filter_one) for a GuidanceConfig."""

    def __init__(self, cfg, safety_cfg: safety.SafetyConfig) -> None:
        """`cfg`: the agent.guidance.GuidanceConfig flown; `safety_cfg`: its policy's filter
        settings (GuidancePolicy.safety_cfg). Raises OSError, FileNotFoundError (no compiler)
        or subprocess.CalledProcessError (the build failed)."""
        from firmware.cpolicy import MAX_INPUTS, MAX_NEIGHBOURS, CPolicy

        wanted = cfg.max_neighbours
        self._policy = CPolicy(
            cfg.policy_path,
            separation_m=cfg.separation_m,
            cruise_speed_m_s=cfg.cruise_speed_m_s,
            max_neighbours=MAX_NEIGHBOURS if wanted is None else min(wanted, MAX_NEIGHBOURS),
            safety_filter=cfg.safety_filter,
            safety_cfg=safety_cfg,
            policy_separation_m=cfg.told_separation_m,
            sparse_rule=cfg.sparse_rule,
            told_sigma_free_m=cfg.told_sigma_free_m,
        )
        self._filter = self._policy._filter
        # numpy's network sees `wanted` neighbours (None: all), the core's at most MAX_NEIGHBOURS
        self._most_decided = (
            MAX_INPUTS if wanted is not None and wanted <= MAX_NEIGHBOURS else MAX_NEIGHBOURS
        )
        self._most_filtered = MAX_INPUTS
        self.calls = {"decide": 0, "filter": 0, "numpy": 0}
        """How many calls the C core answered, and how many it left to numpy (read only)."""
        self._said: set[tuple[str, str]] = set()

    @classmethod
    def maybe(cls, cfg, safety_cfg: safety.SafetyConfig) -> CCore | None:
        """A CCore, or None (logged once) where the library cannot be built or loaded."""
        try:
            return cls(cfg, safety_cfg)
        except (OSError, subprocess.CalledProcessError) as exc:
            log.warning(UNAVAILABLE, exc)
            return None

    def _refused(self, what: str, why: str) -> None:
        """numpy answers a call the core refused; each kind of refusal is logged once (a vehicle
        far from the origin would otherwise log it ten times a second)."""
        self.calls["numpy"] += 1
        if (what, why) not in self._said:
            self._said.add((what, why))
            log.warning("the C core refused %s (%s): numpy answers it, and the like", what, why)

    def decide(
        self, pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, **sky
    ) -> np.ndarray | None:
        """The policy's velocity to hold (2,), unfiltered, as GuidancePolicy.command without its
        filter; None: numpy must answer (more neighbours than the core would see alike, or a
        fault)."""
        if len(nbr_pos_m) > self._most_decided:
            self.calls["numpy"] += 1
            return None
        try:
            out = self._policy.preferred(
                pos_m, vel_m_s, heading_rad, goal_m, nbr_pos_m, nbr_vel_m_s, nbr_heading_rad, **sky
            )
        except ValueError as exc:
            self._refused("a decision", str(exc))
            return None
        self.calls["decide"] += 1
        return out

    def filter(
        self, pos_m, vel_m_s, pref_m_s, nbr_pos_m, nbr_vel_m_s, own_id, nbr_ids, **sky
    ) -> tuple[float, float] | None:
        """policy.safety.filter_one without zones, in C: the filtered (north, east) velocity
        as Python floats (the own vectors may be tuples of two floats: no numpy call); None:
        numpy must answer (more neighbours than the core takes, or a fault)."""
        if len(nbr_pos_m) > self._most_filtered:
            self.calls["numpy"] += 1
            return None
        status, vel_n, vel_e = self._filter.velocity(
            pos_m,
            vel_m_s,
            pref_m_s,
            nbr_pos_m,
            nbr_vel_m_s,
            0 if own_id is None else own_id,
            nbr_ids,
            **sky,
        )
        if status != "ok":
            self._refused("the filter", status)
            return None
        self.calls["filter"] += 1
        return vel_n, vel_e


if __name__ == "__main__":  # an install step: build the library where the agent will load it
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    built = build()
    print("the C guidance core is built" if built else "no C guidance core: agents fly numpy")
    raise SystemExit(0 if built else 1)
