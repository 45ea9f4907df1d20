"""“Did you mean …?” for misspelt names (scenario keys, estimator names, fault kinds, CLI verbs)."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


def closest(word: str, choices: Iterable[str]) -> str | None:
    """The choice nearest to ``word`` if one is near enough (difflib ratio ≥ 0.6, case-insensitive)."""
    choices = [str(c) for c in choices]
    low = {c.lower(): c for c in choices}
    hit = difflib.get_close_matches(str(word).lower(), list(low), n=1, cutoff=0.6)
    return low[hit[0]] if hit else None


def did_you_mean(word: str, choices: Iterable[str], quote: str = "`") -> str:
    """``"did you mean `rounds`? "`` — or ``""`` when nothing is close."""
    hit = closest(word, choices)
    return f"did you mean {quote}{hit}{quote}? " if hit else ""
