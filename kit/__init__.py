"""General helpers that import nothing of covey: bounded reading of user files, the tick
loop, child processes."""
