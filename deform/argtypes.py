"""argparse types for the command lines (``deform``, ``deform-service``): a bad number stops at
parsing, one line naming the option, before any work or any file is made (``--iterations 0`` used to
end in a traceback after the run directory was created)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An integer of at least ``minimum``.

    Args:
        minimum: the smallest value accepted.

    Returns:
        The argparse ``type``.
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer of at least {minimum}, got {value}")
        return value

    return parse


def number(positive: bool) -> Callable[[str], float]:
    """A finite number, > 0 (``positive``) or >= 0 (a duration, a rate, a bound).

    Args:
        positive: 0 is refused too.

    Returns:
        The argparse ``type``.
    """

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value) or value < 0 or (positive and value == 0):
            raise argparse.ArgumentTypeError(f"expected a number {'>' if positive else '>='} 0, got {text}")
        return value

    return parse
