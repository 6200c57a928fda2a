"""`covey demo`'s config: the steady state rate its agents get, and what it refuses."""

from __future__ import annotations

import pytest

from comms.state_rate import MIN_STEADY_STATE_HZ
from groundstation.demo import DemoConfig, parser


def test_agents_publish_at_the_steady_rate_by_default_and_0_turns_it_off() -> None:
    assert DemoConfig().steady_state_hz == MIN_STEADY_STATE_HZ
    assert DemoConfig(steady_state_hz=0).steady_state_hz == 0
    args = parser().parse_args(["--steady-state-hz", "5"])
    assert args.steady_state_hz == 5.0


@pytest.mark.parametrize("hz", [1.0, 2.9, 500.0])
def test_a_steady_rate_receivers_cannot_count_on_is_refused_with_the_reason(hz: float) -> None:
    with pytest.raises(ValueError, match="steady state_hz must be within"):
        DemoConfig(steady_state_hz=hz)


def test_the_demo_builds_the_agents_c_core_once_or_tells_them_to_fly_numpy(capsys) -> None:
    import sys

    from groundstation.demo import C_CORE_BUILD, c_core_flags

    assert c_core_flags(C_CORE_BUILD) == ()  # built (or already): the agents load it
    failing = (sys.executable, "-c", "print('no C compiler here'); raise SystemExit(1)")
    assert c_core_flags(failing) == ("--no-c-core",)
    assert "no C compiler here; the agents fly numpy (--no-c-core)" in capsys.readouterr().out
