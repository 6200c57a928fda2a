"""Where each part of the station's control panel goes, top to bottom (viser GUI `order`).

The kill comes first, right under the title: nothing an operator opens (the command log, a long
ack matrix, the fleet table of a large fleet) can push it below the fold. The command form
follows, then what the operator reads: the fleet, the command log and the events, all open.
Shared parts (title, fleet, command log) and each tab's own parts (kill, form, events) are
interleaved by these numbers.
"""

TITLE = 0.0
KILL = 1.0
MESSAGES = 2.0
COMMAND = 3.0
GOTO = 4.0
FLEET = 5.0
COMMAND_LOG = 6.0
EVENTS = 7.0
