"""The grid of a sweep: ``--grid KEY=V1,V2,…`` axes, their values as TOML, and the runs of their
Cartesian product × seeds."""

from __future__ import annotations

import hashlib
import itertools
import json
import re
import tomllib
from dataclasses import dataclass

import tomli_w

from agent.scenario import ScenarioError


#: grid-key shorthands → dotted scenario keys
SHORTHANDS = {
    "estimator": "estimator.name",
    "rounds": "estimator.rounds",
    "range": "topology.range",
    "link_loss": "faults.link_loss",
    "ticks": "run.ticks",
}


# ============================================================================ the grid

@dataclass(frozen=True)
class Axis:
    key: str      #: the dotted scenario key, e.g. "estimator.rounds"
    label: str    #: what figures and run ids call it (the shorthand when there is one)
    values: tuple

    @property
    def numeric(self) -> bool:
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in self.values)


def split_values(text: str) -> list[str]:
    """Split ``V1,V2,…`` at the commas that are not inside brackets, braces or quotes."""
    out, cur, depth, quote = [], [], 0, ""
    for ch in text:
        if quote:
            cur.append(ch)
            if ch == quote:
                quote = ""
            continue
        if ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur).strip())
    return out


def parse_value(text: str):
    """A TOML value (``0.1``, ``true``, ``[1, 2]``, ``"x"``); anything else is taken as a bare string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def canonical_key(key: str, source: str = "--grid") -> tuple[str, str]:
    """(dotted key, label) for a ``--grid`` key; raises :class:`ScenarioError` for a malformed or reserved one."""
    key = key.strip()
    label = key
    dotted = SHORTHANDS.get(key, key)
    if dotted in ("seed", "run.seed"):
        raise ScenarioError(source, dotted, "the seed is not a grid key", "use --seeds S (runs seeds 0 … S−1)")
    sect, dot, name = dotted.partition(".")
    if not dot or not sect or not name or "." in name:
        raise ScenarioError(source, key, "grid key must look like section.key",
                            f"e.g. --grid estimator.rounds=1,2,5, or a shorthand: {', '.join(SHORTHANDS)}")
    for short, full in SHORTHANDS.items():
        if full == dotted:
            label = short
    return dotted, label


def parse_grid(spec: str) -> Axis:
    """``KEY=V1,V2,…`` → :class:`Axis`."""
    key, sep, vals = spec.partition("=")
    if not sep or not vals.strip():
        raise ScenarioError("--grid", spec, "expected KEY=V1,V2,…", "e.g. --grid 'faults.link_loss=0,0.1,0.3'")
    dotted, label = canonical_key(key)
    raw = split_values(vals)
    if any(r == "" for r in raw):
        raise ScenarioError("--grid", spec, "empty value in the list", "remove the stray comma")
    values = tuple(parse_value(r) for r in raw)
    reprs = [value_repr(v) for v in values]
    dup = sorted({r for r in reprs if reprs.count(r) > 1})
    if dup:
        raise ScenarioError("--grid", spec, f"repeated value(s) {', '.join(dup)}", "list each value once")
    return Axis(dotted, label, values)


def value_repr(v) -> str:
    """How a grid value is written in the CSV, run ids and figure labels (strings bare, the rest as TOML)."""
    if isinstance(v, str):
        return v
    return _toml_inline(v)


def _toml_inline(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_toml_inline(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_inline(x)}" for k, x in v.items()) + "}"
    return tomli_w.dumps({"v": v}).partition("=")[2].strip()


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]+", "x", text.strip("[]{} "))


@dataclass(frozen=True)
class RunSpec:
    run_id: str
    cell_index: int
    cell: tuple   #: values, in axis order
    seed: int


def expand(axes: list[Axis], seeds: list[int]) -> list[RunSpec]:
    """The Cartesian product of the axes × seeds, with stable, readable run ids."""
    cells = list(itertools.product(*(a.values for a in axes))) if axes else [()]
    bases = []
    for cell in cells:
        bases.append("_".join(f"{slug(a.label)}-{slug(value_repr(v))}" for a, v in zip(axes, cell)))
    for ci, cell in enumerate(cells):
        lossy = any(slug(value_repr(v)) != value_repr(v) for v in cell) or len(bases[ci]) > 100
        if lossy or bases.count(bases[ci]) > 1:  # unique and still readable when values had to be mangled
            h = hashlib.sha1(json.dumps([[a.key, value_repr(v)] for a, v in zip(axes, cell)]).encode()).hexdigest()[:8]
            bases[ci] = f"{bases[ci][:80]}~{h}"
    specs: list[RunSpec] = []
    for ci, cell in enumerate(cells):
        for s in seeds:
            specs.append(RunSpec(f"{bases[ci]}_seed-{s}" if bases[ci] else f"seed-{s}", ci, cell, s))
    return specs


