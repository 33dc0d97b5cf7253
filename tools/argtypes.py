"""Command-line helpers shared by the tools: argument types, a parser whose errors are one
line (no usage block, no SystemExit), and the one-line error exit."""

from __future__ import annotations

import argparse
import math
import sys


class UsageError(ValueError):
    """A bad command line (one line, exit 2)."""


class OneLineParser(argparse.ArgumentParser):
    """argparse that raises UsageError instead of printing its usage and exiting."""

    def error(self, message: str):  # type: ignore[override]
        raise UsageError(message)


def fail(text: str, prog: str = "topoexplore") -> int:
    """Print the first line of text as the command's error; exit code 2."""
    print(f"{prog}: {text.splitlines()[0] if text else 'error'}", file=sys.stderr)
    return 2


def _number(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"not a finite number: {text!r}")
    return v


def positive(text: str) -> float:
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0: {text!r}")
    return v


def non_negative(text: str) -> float:
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0: {text!r}")
    return v


def count(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1: {text!r}")
    return v


def port(text: str) -> int:
    if not text.isdigit() or not 0 <= int(text) <= 65535:
        raise argparse.ArgumentTypeError(f"not a port: {text!r}")
    return int(text)
