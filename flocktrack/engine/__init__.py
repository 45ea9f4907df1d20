"""Running a scenario to an output directory: the roles built from a scenario, in one process on LocalBus or
one process per node over Zenoh."""
