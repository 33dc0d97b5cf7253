"""Reliability service: position probability of end nodes (paper eqs. 1-10)."""
