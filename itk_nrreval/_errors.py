"""The one exception type the toolkit raises for bad input.

The CLI turns it into a single line on stderr and exit code 2, so its message must stand
on its own: name the file (or argument) and say what is wrong with it.
"""

from __future__ import annotations

__all__ = ["InputError", "EngineError"]


class InputError(ValueError):
    """Bad input: a file that cannot be read, grids that differ, a malformed manifest.

    Subclasses :class:`ValueError` so library callers can catch either.
    """


class EngineError(RuntimeError):
    """A registration engine failed (crashed, or refused its parameters).

    Not bad input in itself: the message says which engine, which image and why. The CLI
    prints it as one line and exits with code 1.
    """
