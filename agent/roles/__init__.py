"""Process shells: thin, message-driven loops around the pure core.

A role subscribes to a :class:`agent.bus.Bus`, reacts to validated messages in ``on_*`` handlers and
publishes its own. It never blocks: when it waits for messages that may never come (a dead
neighbour, a lost payload), the driver calls :meth:`on_deadline` and the role goes on with what it
has. The same role objects run on the in-process ``LocalBus`` and, one per OS process, over Zenoh.
"""
