"""Importing this module imports every estimator the registry finds (:func:`agent.estimators.registry.specs`).

For the fork-server's template (``flocktrack/launch/forkserver.py``): every role's process reads its scenario,
which asks the registry for the estimators, so each would import all of them (the distributed minimax
filter's gate brings ``scipy.stats``, ~0.35 s of CPU) and scan this package for them. Done once in the
template, the children inherit both the modules and the registry's answer.
"""

from .registry import specs

specs()
