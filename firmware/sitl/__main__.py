"""`python -m firmware.sitl --id N ...`: the same as `covey sitl`."""

from firmware.sitl.cli import cli

raise SystemExit(cli())
