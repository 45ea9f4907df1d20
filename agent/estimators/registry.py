"""Build a node's estimator from a scenario's ``[estimator]`` table (and the runtime's design).

Estimators that need facts about the whole network (Chen's λ₀ over every switching graph) receive
them precomputed in ``design`` (DESIGN.md: the runtime computes graph-wide designs before the run).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..scenario import Scenario
from ..seeding import rng_for
from .base import Estimator

NAMES = ("minimax", "kalman", "hinf_switching", "min_energy")


def make_estimator(sc: Scenario, i: int, design: Mapping[str, Any] | None = None) -> Estimator:
    """Estimator of sensor ``i`` for scenario ``sc``."""
    e = sc.estimator
    m = sc.m
    x0 = sc.initial_estimates()[i]
    P0 = np.eye(m) if e.P0 is None else np.array(e.P0, float)
    if e.name in ("minimax", "kalman"):
        from .distributed_minimax import DistributedKalman, DistributedMinimax

        if e.name == "kalman":
            return DistributedKalman(sc.A, sc.filter_Q(), sc.C, sc.R, sc.sensors.n, x0, P0, e.rounds, e.eta,
                                     e.resilient_f)
        return DistributedMinimax(sc.A, sc.filter_Q(), sc.C, sc.R, np.array(e.S, float), sc.sensors.n, x0, P0,
                                  e.rounds, e.eta, e.resilient_f)
    if e.name == "hinf_switching":
        from .hinf_switching import HinfSwitchingEstimator

        if design is None or "K" not in design:
            raise ValueError("hinf_switching needs the design gain K (computed by the runtime from the schedule)")
        K = np.array(design["K"], float)
        comm = None if e.comm_noise is None else np.array(e.comm_noise, float)
        return HinfSwitchingEstimator(sc.A, sc.C, K, x0, comm_noise_cov=comm,
                                      rng=rng_for(sc.run.seed, "agent", i, "comm_noise"), resilient_f=e.resilient_f)
    if e.name == "min_energy":
        from .min_energy import MinEnergyDesign, MinEnergyNode

        if design is None or "min_energy" not in design:
            raise ValueError("min_energy needs the SDP design (29), computed by the runtime before the run")
        dsg = MinEnergyDesign.from_dict(design["min_energy"])
        return MinEnergyNode.from_design(dsg, i, x0=x0, substeps=e.substeps, method=e.method, hold=e.hold,
                                         rng=rng_for(sc.run.seed, "agent", i, "channel_noise"),
                                         channel_noise_std=e.channel_noise_std)
    raise ValueError(f"unknown estimator {e.name!r}; known: {', '.join(NAMES)}")
