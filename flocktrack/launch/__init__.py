"""Running a flock on this machine: the embedded router, spawning and supervising the plan's processes, and
the commands that look at a running run (ps, status, logs, fault)."""
