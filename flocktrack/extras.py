"""Optional dependencies: which extra of the package brings which module, and the line that says so.

The main job needs none of them. ``pip install 'flocktrack[design]'`` brings cvxpy with its solvers (the
SDP design of the min-energy H∞ filters, the sum-of-norms reference solver), ``flocktrack[figures]``
matplotlib (the sweeps' PNGs, the dashboard's static picture), ``flocktrack[fusion]`` numba (the
compiled kernels of the sum-of-norms fusion: the ``carrillo_*`` scenarios), ``flocktrack[analysis]`` pandas
and pyarrow (a run as tables: ``flocktrack.load``, ``flocktrack export``), ``flocktrack[dask]`` distributed
and bokeh (sweeps on a Dask cluster, with its dashboard: ``flocktrack sweep --executor dask``),
``flocktrack[all]`` all five.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

#: top-level module → the extra that installs it
EXTRA_OF = {"cvxpy": "design", "clarabel": "design", "scs": "design", "matplotlib": "figures", "numba": "fusion",
            "llvmlite": "fusion", "pandas": "analysis", "pyarrow": "analysis",
            "distributed": "dask", "dask": "dask"}


def install_line(extra: str) -> str:
    return f"pip install 'flocktrack[{extra}]'"


def missing_extra(exc: BaseException) -> str | None:
    """The one line for an ImportError of a module that an extra brings, else None (a real bug)."""
    name = (getattr(exc, "name", None) or "").split(".")[0]
    extra = EXTRA_OF.get(name)
    if not isinstance(exc, ImportError) or extra is None:
        return None
    return f"this needs {name}, an optional dependency of flocktrack; install it with: {install_line(extra)}"


def has(module: str) -> bool:
    """Whether ``module`` can be imported (without importing it)."""
    return importlib.util.find_spec(module) is not None


def require(module: str) -> ModuleType:
    """Import ``module``, an optional dependency; where it is missing, raise ModuleNotFoundError whose message
    is :func:`missing_extra`'s line (the CLI prints that line, a caller of the library reads it)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        line = missing_extra(exc)
        if line is None:
            raise
        raise ModuleNotFoundError(line, name=exc.name) from None
