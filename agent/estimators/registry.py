"""The set of estimator specs, and a node's estimator from a scenario.

Every module of this package that declares an :class:`agent.estimators.spec.EstimatorSpec` at module
level is an estimator of the runtime: :func:`specs` finds them (a module is imported only if its source
declares ``EstimatorSpec(``, so the fusion solvers are not loaded by every sensor). An installed package
adds estimators through the entry-point group ``flocktrack.estimators`` (:data:`ENTRY_POINT_GROUP`): each
entry point names an ``EstimatorSpec`` or a ``FusionSpec`` object, its name the spec's name, e.g. in the
plug-in's ``pyproject.toml``::

    [project.entry-points."flocktrack.estimators"]
    toy_average = "toy_estimator:SPEC"

Every process of a run finds them the same way (the sensors too), and their parameters are typed and
checked like the built-in ones'. Estimators that need
facts about the whole network (Chen's λ₀ over every switching graph, Zamani's SDP) receive them
precomputed in ``design`` (DESIGN.md: the runtime computes graph-wide designs before the run).
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from collections.abc import Mapping
from functools import cache
from pathlib import Path
from typing import Any

from .base import Estimator
from .spec import EstimatorSpec, FusionSpec

_HERE = Path(__file__).resolve().parent
ENTRY_POINT_GROUP = "flocktrack.estimators"


def _declared(kind: type, marker: str) -> dict[str, Any]:
    """name → spec of type ``kind`` declared at module level in this package (modules whose source
    contains ``marker``), in module-name order."""
    found: dict[str, Any] = {}
    for mod in sorted(pkgutil.iter_modules([str(_HERE)]), key=lambda m: m.name):
        if mod.name.startswith("_") or mod.ispkg or mod.name in ("spec", "registry"):
            continue
        if marker not in (_HERE / f"{mod.name}.py").read_text(encoding="utf-8"):
            continue
        module = importlib.import_module(f"{__package__}.{mod.name}")
        for value in vars(module).values():
            if isinstance(value, kind):
                if value.name in found and found[value.name] is not value:
                    raise RuntimeError(f"two estimators are named {value.name!r} ({mod.name} and another module)")
                found[value.name] = value
    for name, value, dist in _plugins(kind):
        if name in found:
            raise RuntimeError(f"the estimator plug-in {name!r} of {dist} has the name of another estimator; "
                               f"rename its entry point and spec")
        found[name] = value
    return found


def _plugins(kind: type) -> list[tuple[str, Any, str]]:
    """(name, spec, distribution) of every ``flocktrack.estimators`` entry point whose object is a
    ``kind``. One that cannot be loaded, or is misnamed, is skipped with one line on stderr (the others
    still work; a scenario naming it then gets the unknown-estimator error with the names there are)."""
    from importlib.metadata import entry_points

    out = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        dist = ep.dist.name if ep.dist is not None else "an installed package"
        try:
            value = ep.load()
        except Exception as exc:  # a broken plug-in must not take the built-in estimators down with it
            _skip(ep.name, dist, f"cannot be loaded ({type(exc).__name__}: {exc})")
            continue
        if not isinstance(value, (EstimatorSpec, FusionSpec)):
            _skip(ep.name, dist, f"names a {type(value).__name__}, not an EstimatorSpec or FusionSpec")
        elif value.name != ep.name:
            _skip(ep.name, dist, f"names the spec {value.name!r}: the entry point's name must be the spec's")
        elif isinstance(value, kind):
            out.append((ep.name, value, dist))
    return out


_SKIPPED: set[str] = set()


def _skip(name: str, dist: str, why: str) -> None:
    if name not in _SKIPPED:   # specs() and fusion_specs() both look: say it once
        _SKIPPED.add(name)
        print(f"warning: estimator plug-in {name!r} of {dist} {why}; skipped", file=sys.stderr)


@cache
def specs() -> dict[str, EstimatorSpec]:
    """name → spec of every registered estimator, in module-name order."""
    return _declared(EstimatorSpec, "EstimatorSpec(")


@cache
def fusion_specs() -> dict[str, FusionSpec]:
    """name → spec of every fusion-role estimator (``[fusion] estimator``), in module-name order."""
    return _declared(FusionSpec, "FusionSpec(")


def build_fusion(table: Mapping[str, Any], source: str = "scenario") -> tuple[str, Any]:
    """(name, estimator) of a ``[fusion]`` table: ``estimator`` names the spec (the default spec if
    absent); the other keys are its ``params``, typed and checked (:class:`agent.schema.ScenarioError`
    naming ``source``, the key and the fix)."""
    from ..schema import ScenarioError, build_table, did_you_mean

    have = fusion_specs()
    t = dict(table)
    default = [n for n, s in have.items() if s.default]
    name = t.pop("estimator", default[0] if default else None)
    if name not in have:
        raise ScenarioError(source, "fusion.estimator", f"unknown fusion estimator {name!r}",
                            f"{did_you_mean(str(name), have)}use one of: {', '.join(have)}")
    spec = have[name]
    params = build_table(spec.params, t, source, "fusion")
    spec.check(source, params)
    return name, spec.build(params)


def register(spec: EstimatorSpec) -> None:
    """Add an estimator defined outside this package (a notebook, a test) to the registry of this
    process. An estimator meant for every process of a run goes in a module of this package or in an
    installed package's ``flocktrack.estimators`` entry point (the sensor processes find both)."""
    have = specs()
    if spec.name in have and have[spec.name] is not spec:
        raise ValueError(f"an estimator named {spec.name!r} is already registered")
    have[spec.name] = spec


def unregister(name: str) -> None:
    """Remove an estimator added with :func:`register`."""
    specs().pop(name, None)


def names() -> tuple[str, ...]:
    """The registered estimator names (what ``[estimator] name`` and ``--estimator`` accept)."""
    return tuple(specs())


def default_name() -> str:
    """The estimator of a scenario whose ``[estimator]`` table gives no name (the spec marked default)."""
    marked = [n for n, s in specs().items() if s.default]
    if len(marked) != 1:
        raise RuntimeError(f"exactly one estimator spec must be the default, found {marked}")
    return marked[0]


def spec_of(name: str) -> EstimatorSpec:
    """The spec called ``name`` (KeyError for an unknown name; the scenario loader checks names first)."""
    return specs()[name]


def make_estimator(sc: Any, i: int, design: Mapping[str, Any] | None = None) -> Estimator:
    """Estimator of sensor ``i`` for scenario ``sc`` (with the runtime's pre-run ``design``)."""
    e = sc.estimator
    return spec_of(e.name).build(sc, i, e.params, design or {})
