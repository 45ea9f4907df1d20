"""The estimator plug-in contract: one :class:`EstimatorSpec` per estimator, declared in its own module.

An estimator module of this package declares, at module level, ``SPEC = EstimatorSpec(...)`` (a module
that hosts two related estimators may declare two). :mod:`agent.estimators.registry` finds them; the
scenario loader, the CLI's choices, ``flocktrack design`` and the metrics read them, so adding an
estimator is adding one file (see docs/adding_an_estimator.md). A spec has

``name``       the ``[estimator] name`` that selects it;
``params``     a frozen dataclass: the estimator's own ``[estimator]`` keys — its scenario schema and its
               docs (the common keys ``rounds``, ``eta``, ``Q``, ``P0``, ``x0``, ``x0_offsets``,
               ``resilient_f`` belong to every estimator and stay in :class:`agent.scenario.EstimatorCfg`);
``check``      cross-field validation, ``check(sc, params)``, raising :class:`agent.schema.ScenarioError`
               that names the file, the key and the fix;
``design``     an optional pre-run hook, ``design(sc, params, facts) -> dict``: what needs the whole graph
               (computed once by the runtime, which hands in :class:`GraphFacts`, and given to every
               node; JSON-able). A ``"tmsee_lower"`` list in it is drawn and scored as the TMSEE
               lower bound;
``build``      ``build(sc, i, params, design) -> Estimator``: node ``i``'s estimator;
``summary``    optional extra ``summary.json`` fields, ``summary(design, trace) -> dict`` over the
               finished run's :class:`RunTrace` (None when the run has no complete ticks 0…K);
``report_design``  optional ``report_design(design) -> (to_store, message)`` for ``flocktrack design``
               (default: the whole design and its keys);
``per_sensor_C``   whether sensors may each have their own C (``[sensors] C`` as a list of matrices);
``default``        whether it is the estimator of a scenario that names none (exactly one spec says so).

Hooks receive the scenario as an object (typed ``Any`` here: the scenario module imports this one).

The fusion role of a UAV scenario (García Carrillo et al.; ``[fusion]`` in scenarios/carrillo_uav.toml)
runs a different kind of estimator — a stream of time-stamped relative measurements, ``add(meas)`` then
``solve()`` — and its modules declare a :class:`FusionSpec` instead: ``name`` (``[fusion] estimator``),
``params`` (a frozen dataclass: the estimator's own ``[fusion]`` keys, typed and checked like the
``[estimator]`` keys), ``build(params)`` and an optional ``check(source, params)``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .base import Estimator


@dataclass(frozen=True)
class NoParams:
    """An estimator with no keys of its own."""


@dataclass(frozen=True)
class GraphFacts:
    """What the runtime knows about the whole graph before the run (DESIGN.md: designs that need the
    whole graph are computed by the runtime and handed to each sensor).

    ``H_graphs``: H = L + B of each distinct graph of a switching schedule (None for a range topology,
    whose graphs are not known in advance); ``H_per_tick``: H of the graph in force at each tick k
    (None for a range topology); ``stored(path)``: a stored design file's JSON mapping (a relative path
    is taken from the scenario file's directory) — the hook never opens files itself."""

    H_graphs: Sequence[np.ndarray] | None = None
    H_per_tick: Sequence[np.ndarray] | None = None
    stored: Callable[[str], Mapping[str, Any]] | None = None


@dataclass(frozen=True)
class RunTrace:
    """A finished run, tick by tick, for an estimator's summary fields.

    ``T``: the tick period (s); ``errors``: (K+1, n, m) node estimates minus the truth over the ticks
    0…K that every node estimated; ``w``: (K, ·) the target's process disturbance per tick;
    ``v``: per node, (K, q) its measurement noise per tick; ``extra(k, i, name)``: a vector node i
    reported beside its estimate at tick k (e.g. the channel noise ``eps_<j>``), or None."""

    T: float
    errors: np.ndarray
    w: np.ndarray
    v: Sequence[np.ndarray]
    extra: Callable[[int, int, str], np.ndarray | None]


def _no_check(sc: Any, params: Any) -> None:
    """Nothing beyond the parameters' types."""


@dataclass(frozen=True)
class EstimatorSpec:
    name: str
    build: Callable[[Any, int, Any, Mapping[str, Any]], Estimator]
    params: type = NoParams
    check: Callable[[Any, Any], None] = _no_check
    design: Callable[[Any, Any, GraphFacts], dict[str, Any]] | None = None
    summary: Callable[[Mapping[str, Any], RunTrace | None], dict[str, Any]] | None = None
    report_design: Callable[[dict[str, Any]], tuple[dict[str, Any], str]] | None = None
    per_sensor_C: bool = False
    default: bool = False        #: the estimator of a scenario whose [estimator] gives no name (one spec)
    doc: str = field(default="", compare=False)

    def param_names(self) -> list[str]:
        """The estimator's own ``[estimator]`` keys."""
        return list(self.params.__dataclass_fields__)


def _no_fusion_check(source: str, params: Any) -> None:
    """Nothing beyond the parameters' types."""


@dataclass(frozen=True)
class FusionSpec:
    """A fusion-role estimator (module doc): ``[fusion] estimator = name`` and its own keys ``params``."""

    name: str
    build: Callable[[Any], Any]
    params: type = NoParams
    check: Callable[[str, Any], None] = _no_fusion_check
    default: bool = False        #: the estimator of a [fusion] table that names none (one spec)
    doc: str = field(default="", compare=False)
    #: ``[fusion] mode = "distributed"``: UAV i's node from the built estimator (its settings), ``records``
    #: (tick → that UAV's own measurements), ``iterations`` and ``rho`` of the consensus, and the tick ``T``;
    #: None: this estimator runs centrally only
    distributed: Callable[..., Any] | None = field(default=None, compare=False)

    def param_names(self) -> list[str]:
        return list(self.params.__dataclass_fields__)
