"""Tools that work on recordings of a fleet: `covey record`, `covey replay` and closed-loop
replay of one vehicle through a policy.

They sit at the top with the ground station (comms <- policy <- agent <- groundstation and
tools): closed-loop replay runs the agent's guidance, which comms/ and groundstation/ must not
import.
"""
