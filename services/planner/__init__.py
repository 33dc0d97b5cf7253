"""Exploration planner: target choice and paths (reliability | all-end-nodes | frontier).

``core.PlannerCore`` is the pure core used by ``service.py``; ``graph`` holds the topological
search, ``frontier`` the frontier detection and grid path search.
"""
