"""What every covey command line shares: mesh and key-file options, unit-checked value
types, flags built from config dataclasses."""
