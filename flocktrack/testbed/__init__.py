"""Emulated testbeds on one machine, to rehearse a deployment before the real hosts: several hosts as Linux
network namespaces joined by a switch (:mod:`~flocktrack.testbed.netns`), a private Docker engine for a
compose deployment (:mod:`~flocktrack.testbed.docker`), and the system tools they need
(:mod:`~flocktrack.testbed.tools`). The multi-host and container tests and benchmarks run on them."""
