"""Typed tables from TOML: the checking every scenario section (and every estimator's parameters) shares.

A section is a frozen dataclass; :func:`build_table` turns a TOML table into it, coercing each value to
the field's annotation (numbers, strings, ``Literal`` choices, vectors, matrices, lists of matrices,
``[i, j]`` pairs, arrays of sub-tables) and raising :class:`ScenarioError` that names the file, the key
and the fix — with "did you mean" for a misspelt key or choice. :func:`check_shape` and :func:`check_pd`
are the cross-field checks of matrices. Pure: no file is read here.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Collection
from typing import Any, Literal

import numpy as np

from .suggest import did_you_mean

#: Limits on what a scenario may ask for — refused with the file/key/fix error while the file is read, before
#: anything is built or any process starts (a 10⁴ × 10⁴ matrix is refused at its first row, not parsed).
LIMITS = {
    "list_len": 4096,      #: entries of any list (a vector, a matrix's rows) — the wire's MAX_LIST_LEN
    "matrix_cols": 64,     #: columns of any matrix: state, measurement and noise dimensions are ≤ 64
    "sensors": 1000,       #: sensors.n (one OS process each over Zenoh)
    "ticks": 10**8,        #: run.ticks
    "T_min": 1e-6,         #: run.T (s): the model's sample time
    "realtime_tick_min": 1e-3,   #: run.T / run.speed (s) in realtime: no process keeps a faster clock
    "file_bytes": 16 * 2**20,    #: a scenario file (refused unread beyond)
}

Matrix = list[list[float]]
Vector = list[float]
Matrices = list[list[list[float]]]   #: one matrix per sensor (or per edge)
Pairs = list[list[int]]              #: [i, j] integer pairs


class ScenarioError(ValueError):
    """A scenario that cannot run. The message names the file, the key, and the fix."""

    def __init__(self, source: str, key: str, problem: str, fix: str = ""):
        self.source, self.key, self.problem, self.fix = source, key, problem, fix
        msg = f"{source}: [{key}] {problem}"
        if fix:
            msg += f" — fix: {fix}"
        super().__init__(msg)


def describe(tp: Any) -> str:
    """What a value of schema type ``tp`` looks like, in words."""
    named = {float: "a number", int: "an integer", str: "a string", bool: "true or false"}
    if tp in named:
        return named[tp]
    if typing.get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    shapes = {"Matrix": (Matrix, "a matrix (list of equal-length lists of numbers)"),
              "Vector": (Vector, "a list of numbers"),
              "Matrices": (Matrices, "a list of matrices (one per sensor or edge)"),
              "Pairs": (Pairs, "a list of [i, j] integer pairs")}
    for shape, words in shapes.values():
        if tp == shape:
            return words
    return str(tp)


def _union(value: Any, args: tuple, src: str, key: str) -> Any:
    if value is None and type(None) in args:
        return None
    inner = [a for a in args if a is not type(None)]
    if Matrices in inner and Matrix in inner:
        # a list of matrices is three levels deep; a matrix two
        deep = isinstance(value, list) and value and isinstance(value[0], list) and value[0] \
            and isinstance(value[0][0], list)
        return coerce(value, Matrices if deep else Matrix, src, key)
    return coerce(value, inner[0], src, key)


def _scalar(value: Any, tp: Any, bad: ScenarioError) -> Any:
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if not isinstance(value, tp):   # str, bool
        raise bad
    return value


def _choice(value: Any, tp: Any, bad: ScenarioError, src: str, key: str) -> Any:
    args = typing.get_args(tp)
    if value in args:
        return value
    hint = did_you_mean(value, args, quote="'") if isinstance(value, str) else ""
    if hint:
        raise ScenarioError(src, key, bad.problem, f"{hint}write {key} as {describe(tp)}")
    raise bad


def _short(value: Any) -> str:
    """A value for an error message: its repr, cut short (a huge list is not printed whole)."""
    import reprlib

    r = reprlib.Repr()
    r.maxlist, r.maxstring, r.maxother, r.maxlevel = 6, 60, 60, 3
    return r.repr(value)


def _matrix(value: Any, bad: ScenarioError, src: str, key: str) -> Matrix:
    if not isinstance(value, list) or not value or not all(isinstance(r, list) for r in value):
        raise bad
    cols = max(len(r) for r in value)
    if cols > LIMITS["matrix_cols"]:
        raise ScenarioError(src, key, f"{cols} columns; at most {LIMITS['matrix_cols']} are accepted (state, "
                            "measurement and noise dimensions)", "give a smaller model")
    rows = [coerce(r, Vector, src, f"{key}[{i}]") for i, r in enumerate(value)]
    if len({len(r) for r in rows}) != 1 or not rows[0]:
        raise ScenarioError(src, key, "matrix rows have different lengths", "give every row the same length")
    for i, r in enumerate(rows):
        if not all(math.isfinite(x) for x in r):
            raise ScenarioError(src, f"{key}[{i}]", "matrix entries must be finite")
    return rows


def _pairs(value: Any, bad: ScenarioError, src: str, key: str) -> Pairs:
    if not isinstance(value, list):
        raise bad
    for i, e in enumerate(value):
        if (not isinstance(e, list) or len(e) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in e)):
            raise ScenarioError(src, f"{key}[{i}]", f"expected an [i, j] integer pair, got {e!r}")
    return [list(e) for e in value]


def _tables(value: Any, cls: type, src: str, key: str) -> list:
    if not isinstance(value, list):
        raise ScenarioError(src, key, "expected an array of tables", f"write [[{key}]] blocks")
    return [build_table(cls, t, src, f"{key}[{i}]") for i, t in enumerate(value)]


def coerce(value: Any, tp: Any, src: str, key: str) -> Any:
    """``value`` as schema type ``tp``, or :class:`ScenarioError` naming ``key``."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (types.UnionType, typing.Union):
        return _union(value, args, src, key)
    bad = ScenarioError(src, key, f"expected {describe(tp)}, got {_short(value)}", f"write {key} as {describe(tp)}")
    if isinstance(value, list) and len(value) > LIMITS["list_len"]:
        raise ScenarioError(src, key, f"{len(value)} entries; at most {LIMITS['list_len']} are accepted",
                            "a scenario's vectors and matrices are small (see agent/schema.py LIMITS)")
    if tp in (float, int, str, bool):
        return _scalar(value, tp, bad)
    if origin is Literal:
        return _choice(value, tp, bad, src, key)
    if tp == Vector:
        if not isinstance(value, list):
            raise bad
        return [coerce(v, float, src, f"{key}[{i}]") for i, v in enumerate(value)]
    if tp == Matrices:
        if not isinstance(value, list) or not value or not all(
                isinstance(r, list) and r and all(isinstance(x, list) for x in r) for r in value):
            raise bad
        return [coerce(M, Matrix, src, f"{key}[{i}]") for i, M in enumerate(value)]
    if tp == Matrix:
        return _matrix(value, bad, src, key)
    if tp == Pairs:
        return _pairs(value, bad, src, key)
    if origin is list and args and dataclasses.is_dataclass(args[0]):
        return _tables(value, args[0], src, key)
    raise AssertionError(f"unsupported schema type {tp}")  # pragma: no cover


def build_table(cls: type, table: Any, src: str, section: str, required: Collection[str] = (),
                also_known: Collection[str] = ()) -> Any:
    """The dataclass ``cls`` from TOML ``table`` (section ``section`` of file ``src``).

    ``required`` names keys that must be present; ``also_known`` keys are accepted here but left
    for someone else (e.g. an estimator's own parameters beside the common ``[estimator]`` keys)."""
    if not isinstance(table, dict):
        raise ScenarioError(src, section, f"expected a table, got {table!r}", f"write [{section}] as a TOML table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    known = names | set(also_known)
    for k in table:
        if k not in known:
            raise ScenarioError(src, f"{section}.{k}", "unknown key",
                                f"{did_you_mean(k, known)}remove it or use one of: {', '.join(sorted(known))}")
    kw = {}
    for name in (f.name for f in dataclasses.fields(cls) if f.init):
        key = f"{section}.{name}"
        if name not in table:
            if name in required:
                raise ScenarioError(src, key, "is required", f"add {name} = … to [{section}]")
            continue
        kw[name] = coerce(table[name], hints[name], src, key)
    return cls(**kw)


def check_shape(src: str, key: str, M: Any, shape: tuple[int, int], what: str) -> None:
    """``M`` must be a ``shape`` matrix (``what`` says which, e.g. "q × q with q = 2")."""
    got = np.shape(np.array(M, float))
    if got != shape:
        raise ScenarioError(src, key, f"expected a {shape[0]}×{shape[1]} matrix ({what}), got shape "
                            f"{'×'.join(map(str, got))}", f"give {key} {shape[0]} rows of {shape[1]} numbers")


def check_pd(src: str, key: str, M: Any, semi: bool = False) -> None:
    """``M`` must be a symmetric positive definite (``semi``: semidefinite) covariance."""
    M = np.array(M, float)
    if not np.allclose(M, M.T, atol=1e-12):
        raise ScenarioError(src, key, "covariance must be symmetric", "make the matrix symmetric")
    lo = float(np.linalg.eigvalsh(M).min())
    if (lo < 0) if semi else (lo <= 0):
        kind = "positive semidefinite" if semi else "positive definite"
        raise ScenarioError(src, key, f"covariance must be {kind} (smallest eigenvalue {lo:.3g})",
                            f"use a {kind} matrix, e.g. a diagonal with {'non-negative' if semi else 'positive'} entries")


def check_covariance(src: str, key: str, M: Any, n: int, what: str, semi: bool = False) -> None:
    """``M`` is an ``n × n`` covariance: :func:`check_shape` then :func:`check_pd`."""
    check_shape(src, key, M, (n, n), what)
    check_pd(src, key, M, semi=semi)
