"""Topology service: thinning-based topological map (pure core in core.py)."""
