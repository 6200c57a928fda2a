"""Recording a fleet's mesh to MCAP, replaying it, and Foxglove's view of it (in a file
or live)."""
