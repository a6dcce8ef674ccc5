"""Option parsers shared by the sub-commands: each value is checked when it is parsed.

Every parser raises ``argparse.ArgumentTypeError`` with a message that says what was
expected; the command-line parser prints it as one line and exits with code 2.
"""

from __future__ import annotations

import argparse
import math

__all__ = [
    "OneLineParser",
    "add_quiet_option",
    "integer",
    "samples",
    "seed",
    "fraction",
    "positive",
    "at_least_one",
    "MAX_SAMPLES",
]

MAX_SAMPLES = 1 << 36  # the sample counter's range (itk_nrreval.measures._search.sampling)


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line on stderr (exit code 2)."""

    def error(self, message: str):  # noqa: D102 - argparse's hook
        self.exit(2, f"{self.prog}: error: {message}\n")


def _as_integer(text: str) -> int | None:
    """``"100000"`` and ``"1e5"`` are integers; ``"1.5"``, ``"x"`` are not."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        return None
    return int(value) if math.isfinite(value) and value.is_integer() else None


def integer(minimum: int, maximum: int | None = None):
    """A parser of integers in [minimum, maximum] (``1e5`` accepted)."""

    def parse(text: str) -> int:
        value = _as_integer(text)
        if value is None or value < minimum or (maximum is not None and value > maximum):
            bound = f">= {minimum}" if maximum is None else f"in [{minimum}, {maximum}]"
            raise argparse.ArgumentTypeError(f"expected an integer {bound}, got {text!r}")
        return value

    return parse


def samples(text: str) -> int:
    """A number of model samples M: an integer in [2, 2**36)."""
    value = _as_integer(text)
    if value is None or value < 2:
        raise argparse.ArgumentTypeError(f"expected an integer >= 2, got {text!r}")
    if value >= MAX_SAMPLES:
        raise argparse.ArgumentTypeError(
            f"{text!r} is more samples than the sampler can number (at most {MAX_SAMPLES - 1}); "
            "at about 0.2 ns per distance term, M = 1e9 with N = 36 already takes minutes"
        )
    return value


def seed(text: str) -> int:
    """A random seed: an integer in [0, 2**63)."""
    return integer(0, (1 << 63) - 1)(text)


def _number(text: str, ok, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not ok(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def ratio_or_off(text: str) -> float | None:
    """A finite number > 1, or ``off`` (None)."""
    if text.strip().lower() == "off":
        return None
    return _number(text, lambda v: 1 < v < math.inf, "a number > 1, or off")


def positive_or_off(text: str) -> float | None:
    """A finite number > 0, or ``off`` (None)."""
    if text.strip().lower() == "off":
        return None
    return _number(text, lambda v: 0 < v < math.inf, "a positive number, or off")


def fraction(text: str) -> float:
    """A number in [0, 1]."""
    return _number(text, lambda v: 0 <= v <= 1, "a fraction in [0, 1]")


def positive(text: str) -> float:
    """A finite number > 0."""
    return _number(text, lambda v: 0 < v < math.inf, "a positive number")


def at_least_one(text: str) -> float:
    """A finite number >= 1 (a ratio of 'better than')."""
    return _number(text, lambda v: 1 <= v < math.inf, "a number >= 1")


def add_quiet_option(parser: argparse.ArgumentParser) -> None:
    """``--quiet`` (alias ``--no-progress``): no progress bars on stderr, for logs."""
    parser.add_argument(
        "--quiet",
        "--no-progress",
        dest="quiet",
        action="store_true",
        help="no progress bars (for logs)",
    )
