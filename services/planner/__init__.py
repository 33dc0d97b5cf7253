"""Exploration planner: target choice and paths (reliability | all-end-nodes | frontier).

``core.PlannerCore`` is the pure core used by ``service.py``: a strategy from ``strategies/``
(one module each, plus the completion rules) finds the candidates on a per-update
``mapview.MapView``, and the core's decision machine (``decision``) follows one. Kernels:
``graph`` (topological search) and ``gridsearch`` (grid path search and frontier groups).
"""
