"""The programs people run: the ``topoexplore`` command and its subcommands.

``cli`` (the console command), ``run`` (an exploration with a report), ``bench`` (benchmarks),
``keys`` (inspection of the bus), ``render`` and ``draw`` (pictures), ``launch`` (profiles and the
supervisor), ``router`` (a Zenoh router process). Tools may import ``services``, ``sim`` and
``common``; nothing below imports tools (``pyproject.toml``, ``[tool.importlinter]``).
"""
