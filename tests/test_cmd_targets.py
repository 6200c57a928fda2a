"""`covey cmd ... --to` with ids out of range: one line naming the flag, exit 2 (issue 39 #13;
before, `--to 0` printed the parent parser's usage and "Targets: '0' must be ids within ...")."""

from __future__ import annotations

import pytest

from groundstation.ops import cmd_cli


@pytest.mark.parametrize(
    ("to", "why"),
    [
        ("0", "--to '0': vehicle ids start at 1"),
        ("0-3", "--to '0-3': vehicle ids start at 1"),
        ("3-1", "--to '3-1': a range is low-high"),
        ("70000", "--to '70000': vehicle ids end at 65000"),
    ],
)
def test_bad_targets_are_one_line(to, why, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        cmd_cli(["takeoff", "5", "--to", to])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err == f"covey cmd: error: takeoff: {why}\n", err
