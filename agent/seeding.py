"""Deterministic random streams: every draw comes from a generator seeded by (scenario seed, role, id,
stream) (DESIGN.md, "Determinism"), so a role's numbers do not depend on which process runs it."""

from __future__ import annotations

import zlib

import numpy as np


def _code(name: str) -> int:
    return zlib.crc32(name.encode())


def rng_for(seed: int, role: str, ident: int = 0, stream: str = "main") -> np.random.Generator:
    """Independent generator for (seed, role, id, stream)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), _code(role), int(ident), _code(stream)]))
