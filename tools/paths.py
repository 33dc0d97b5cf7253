"""Where the tools find files that live beside the package: a source checkout and ``../shared``.

Installed from a wheel there is no checkout; the tools then look relative to the current
directory only.
"""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1]  # topoexplore/ (or the checkout's root)


def checkout_root() -> Path | None:
    """The repository root when running from a source checkout (editable install), else None."""
    return PACKAGE_ROOT if (PACKAGE_ROOT / "pyproject.toml").is_file() else None


def shared_maps_dir() -> Path | None:
    """``../shared/maps`` beside the current directory or beside the checkout, if it exists."""
    bases = [Path.cwd()]
    root = checkout_root()
    if root is not None:
        bases.append(root)
    for base in bases:
        d = Path(os.path.abspath(base.parent / "shared" / "maps"))  # symlinks kept
        if d.is_dir():
            return d
    return None
