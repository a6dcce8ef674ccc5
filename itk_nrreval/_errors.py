"""The one exception type the toolkit raises for bad input.

The CLI turns it into a single line on stderr and exit code 2, so its message must stand
on its own: name the file (or argument) and say what is wrong with it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["InputError", "EngineError", "readable"]


class InputError(ValueError):
    """Bad input: a file that cannot be read, grids that differ, a malformed manifest.

    Subclasses :class:`ValueError` so library callers can catch either.
    """


class EngineError(RuntimeError):
    """A registration engine failed (crashed, or refused its parameters).

    Not bad input in itself: the message says which engine, which image and why. The CLI
    prints it as one line and exits with code 1.
    """


def readable(value) -> str:
    """`value` as a person writes it in a message: ``-62.0``, ``0.3``, ``[1, 2]``, ``'l3'``.

    numpy scalars and arrays (whose repr is ``np.float64(-62.0)``, ``np.float32(0.3)``,
    ``array([1, 1])``) as plain numbers in their own precision, sequences of them as a
    list or tuple; strings quoted; anything else by its repr.
    """
    if isinstance(value, np.ndarray):
        return readable(list(value.ravel()) if value.ndim else value[()])
    if isinstance(value, np.str_):
        return repr(str(value))
    if isinstance(value, np.generic):
        return str(value)  # the shortest text that reads back as the same value of its type
    if isinstance(value, (list, tuple)):
        items = ", ".join(readable(v) for v in value)
        if isinstance(value, list):
            return f"[{items}]"
        return f"({items},)" if len(value) == 1 else f"({items})"
    return repr(value)
