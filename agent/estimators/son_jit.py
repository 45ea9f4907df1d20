"""numba compilation of the sum-of-norms kernels, with one on-disk cache for all of them.

Every compiled function of the ``son_*`` modules is declared with :func:`kernel`, which is
``njit(cache=True, error_model="numpy")`` with two differences:

* **One cache family.** numba caches a compiled function beside its source
  (``__pycache__/<module>.<function>-<line>.py311.{nbi,nbc}``) and drops the entry only when *that
  function's file* changes (its mtime and size), yet a compiled caller embeds its callees: a kernel
  calling one in another file would keep running the old callee after that file was edited.
  :func:`kernel` stamps every kernel's cache with the mtime and size of *all* ``son_*.py`` files of this
  package instead (:class:`FamilyCache`), so that an edit to any of them recompiles every kernel, as if
  they were one file.
* **Pieces of one loop.** ``@kernel(inline=True)`` (numba's ``inline="always"``) marks a piece split out
  of a larger kernel for reading only: it is compiled into its caller's IR. A call between separately
  compiled kernels costs a reference-count update per array argument, which the interior-point loop
  (:mod:`son_ipm`) and the chain factorisation (:mod:`son_banded`) would otherwise pay at every
  iteration.
"""

from __future__ import annotations

import functools
from pathlib import Path

from numba import njit
from numba.core.caching import FunctionCache, IndexDataCacheFile
from numba.core.dispatcher import Dispatcher

__all__ = ["FamilyCache", "family_stamp", "kernel"]

_HERE = Path(__file__).resolve().parent


@functools.cache
def family_stamp() -> tuple:
    """(file name, mtime, size) of every ``son_*.py`` file of this package: the freshness stamp of
    every kernel's cache entry (read once per process)."""
    out = []
    for p in sorted(_HERE.glob("son_*.py")):
        st = p.stat()
        out.append((p.name, st.st_mtime, st.st_size))
    return tuple(out)


class FamilyCache(FunctionCache):
    """numba's per-function disk cache, fresh only while no ``son_*.py`` file has changed."""

    def __init__(self, py_func):
        super().__init__(py_func)
        # the same index file as FunctionCache, with the family's stamp instead of the function's file's
        self._cache_file = IndexDataCacheFile(cache_path=self._cache_path, filename_base=self._impl.filename_base,
                                              source_stamp=family_stamp())


def kernel(fn=None, *, inline: bool = False):
    """``njit(cache=True, error_model="numpy")`` with the cache of :class:`FamilyCache`;
    ``@kernel(inline=True)`` also inlines the function into its callers (module doc)."""
    if fn is None:
        return functools.partial(kernel, inline=inline)
    disp = njit(error_model="numpy", inline="always" if inline else "never")(fn)
    if isinstance(disp, Dispatcher):  # NUMBA_DISABLE_JIT=1 returns the Python function itself
        disp._cache = FamilyCache(fn)  # what Dispatcher.enable_caching() (cache=True) installs
    return disp
