"""Exploration strategies, one module each, chosen by name (``planner.strategy``).

:data:`REGISTRY` has exactly the names of :data:`topoexplore.common.params.STRATEGIES`.
"""

from __future__ import annotations

from collections.abc import Callable

from topoexplore.services.planner.strategies.all_end_nodes import AllEndNodes
from topoexplore.services.planner.strategies.base import (
    Candidate,
    Config,
    Evaluation,
    Strategy,
    Update,
)
from topoexplore.services.planner.strategies.frontier import Frontier
from topoexplore.services.planner.strategies.reliability import Reliability

__all__ = ["REGISTRY", "make", "Candidate", "Config", "Evaluation", "Strategy", "Update"]

REGISTRY: dict[str, Callable[[Config], Strategy]] = {
    "reliability": Reliability,
    "all-end-nodes": AllEndNodes,
    "frontier": Frontier,
}


def make(cfg: Config) -> Strategy:
    """The strategy cfg.params.strategy names."""
    return REGISTRY[cfg.params.strategy](cfg)
