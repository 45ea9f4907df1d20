"""Estimators: pure, transport-free numpy objects (one filter per file, FilterPy style).

Every distributed estimator implements :class:`agent.estimators.base.Estimator`; the registry
:func:`agent.estimators.registry.make_estimator` builds one from a scenario's estimator table.
"""
