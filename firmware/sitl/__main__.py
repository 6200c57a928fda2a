"""`python -m firmware.sitl --id N ...`: the same as `covey sitl`."""

from firmware.sitl.sitl_cli import cli

raise SystemExit(cli())
