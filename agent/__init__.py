"""flocktrack floor 1: one process = one agent.

The pure algorithm core (``agent.estimators``, ``agent.control``, ``agent.models``) never imports a
bus, msgpack, zenoh, viser or the filesystem; the roles (``agent.roles``) are thin loops around it.
"""
