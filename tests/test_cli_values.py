"""Values a CLI accepts are used, or refused with the real reason (exit 2, before anything starts)."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("start", ["1e30,0", "0,-2e6"])
def test_agent_refuses_a_start_no_state_could_carry(start, capsys) -> None:
    from agent import agent_cli as cli

    with pytest.raises(SystemExit) as exc:
        cli.cli(["--id", "1", "--start-ne-m", start])  # refused before any backend or mesh exists
    assert exc.value.code == 2 and "each coordinate must be within" in capsys.readouterr().err


@pytest.mark.parametrize("bad", ["-inf", "-NaN", "-infinity"])
def test_cmd_says_a_non_finite_coordinate_is_the_problem(bad, capsys) -> None:
    from groundstation.ops import cmd_cli

    with pytest.raises(SystemExit) as exc:
        cmd_cli(["goto", bad, "0", "-5", "--to", "1"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "must be finite numbers" in err and "required" not in err
