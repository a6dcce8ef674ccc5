"""Numbers as every report prints them: significant digits, percentages, a dash for none."""

from __future__ import annotations

import math

__all__ = ["format_number", "format_percent"]


def format_number(v, digits: int = 4) -> str:
    """`v` to `digits` significant digits; an en dash for None or NaN."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.{digits}g}"


def format_percent(v) -> str:
    """A percentage with one decimal; an en dash for None."""
    return "–" if v is None else f"{v:.1f}%"
