"""What the optional parts of the package need (``pyproject.toml``, optional dependencies).

A robot installs the core only; a command that needs an extra says which one in one line
instead of failing somewhere inside a child process.
"""

from __future__ import annotations

import importlib

EXTRA_OF = {"pymunk": "sim", "tqdm": "sim", "matplotlib": "bench", "skimage": "skimage",
            "mcap": "record", "foxglove": "record", "rosbags": "ros2"}


class ExtraMissing(RuntimeError):
    """A module of an optional extra is not installed."""


def require(*modules: str, what: str) -> None:
    """Raise ExtraMissing (one line, naming the pip extra) unless every module imports."""
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            extra = EXTRA_OF.get(name, name)
            raise ExtraMissing(f"{what} needs the optional '{extra}' part ({name} is not "
                               f"installed): pip install 'topoexplore[{extra}]'") from None
