"""Where each part of the station's control panel goes, top to bottom (viser GUI `order`).

The kill is not in the control panel at all: it has a window of its own floating over the 3D
view (`KILL_WINDOW`), so nothing an operator opens or scrolls in the panel (the command log, a long
ack matrix, the fleet table of a large fleet) can push it out of view. In the panel, the messages
come first, then the command form, then what the operator reads: the fleet, the command log and
the events, all open. Shared parts (title, fleet, command log) and each tab's own parts (form,
events) are interleaved by these numbers.
"""

TITLE = 0.0
KILL = 1.0
MESSAGES = 2.0
COMMAND = 3.0
GOTO = 4.0
FLEET = 5.0
TRAFFIC = 5.5
COMMAND_LOG = 6.0
EVENTS = 7.0

KILL_WINDOW = {"x": 70.0, "y": -15.0, "width": 250.0}
"""Where the kill window floats, in CSS pixels (viser `PanelHandle.float`): bottom-left of the 3D
view, clear of the axes widget, away from the control panel on the right."""
