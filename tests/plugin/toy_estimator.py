"""A toy estimator: the whole of what adding an estimator takes (docs/adding_an_estimator.md walks through it).

Model: x_{k+1} = A x_k + w_k, y_i = C x_k + v_i. Node i corrects its prediction with its own measurement
and then pulls toward its neighbours' corrected estimates (one consensus round per exchange round):

    x̂ᵢ ← x̂ᵢ + gain · C⁺ (yᵢ − C x̂ᵢ)          (local correction; b = 0 skips it)
    x̂ᵢ ← x̂ᵢ + η Σⱼ (x̂ⱼ − x̂ᵢ)                 (each round; η = consensus_rate(δ_max))
    x̂ᵢ ← A x̂ᵢ                                (prediction for the next tick)

It is not from the papers and not a good filter; it is short. Placed in ``agent/estimators/`` the module
would be found by the registry as it is; kept here, it is a plug-in package of its own (``pyproject.toml``
beside it declares the ``flocktrack.estimators`` entry point), and tests that do not install it add it
with ``registry.register(SPEC)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.estimators.base import Estimator, Payload, TickContext, valid_inbox
from agent.estimators.consensus import consensus_rate, consensus_round
from agent.estimators.spec import EstimatorSpec
from agent.schema import ScenarioError


class ToyAverage(Estimator):
    def __init__(self, A: np.ndarray, C: np.ndarray, x0: np.ndarray, gain: float, rounds: int, eta_rule: str):
        self.A, self.C = np.asarray(A, float), np.asarray(C, float)
        self.C_pinv = np.linalg.pinv(self.C)
        self._x = np.array(x0, float)
        self.gain, self.rounds, self.eta_rule = float(gain), int(rounds), eta_rule
        self._ctx: TickContext | None = None

    def start(self, ctx: TickContext, y: np.ndarray) -> None:
        self._ctx = ctx
        if ctx.b > 0:
            self._x = self._x + self.gain * self.C_pinv @ (np.asarray(y, float) - self.C @ self._x)

    def payload(self, r: int) -> Payload:
        return {"x": self._x.copy()}

    def absorb(self, r: int, inbox: Mapping[int, Payload]) -> None:
        ctx = self._ctx
        good = valid_inbox({j: p for j, p in inbox.items() if j in ctx.neighbours}, self.payload_shapes())
        eta = consensus_rate(ctx.delta_max, self.eta_rule)
        self._x = consensus_round({"x": self._x}, good, eta, keys=("x",))["x"]

    def finish(self) -> None:
        self._x = self.A @ self._x
        self._ctx = None

    @property
    def x(self) -> np.ndarray:
        return self._x

    def payload_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"x": self._x.shape}

    def _set_x(self, x: np.ndarray) -> None:
        self._x = np.array(x, float)


@dataclass(frozen=True)
class ToyParams:
    """``[estimator]`` keys of the toy: ``gain`` of the local correction, in (0, 1]."""

    gain: float = 0.5


def _check(sc: Any, p: ToyParams) -> None:
    if not 0 < p.gain <= 1:
        raise ScenarioError(sc.source, "estimator.gain", f"must be in (0, 1], got {p.gain}", "e.g. gain = 0.5")


def _build(sc: Any, i: int, p: ToyParams, design: Mapping[str, Any]) -> ToyAverage:
    e = sc.estimator
    return ToyAverage(sc.A, sc.C, sc.initial_estimates()[i], p.gain, e.rounds, e.eta)


SPEC = EstimatorSpec(name="toy_average", params=ToyParams, check=_check, build=_build,
                     doc="a toy: local correction, then neighbour averaging")
