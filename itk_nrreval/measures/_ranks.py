"""How :func:`itk_nrreval.evaluate` ranks registrations by a measure: which direction is
better (:func:`higher_is_better`), rank order (:func:`ranks`) and relative rank in percent
(:func:`relative_ranks`), scores tied within noise sharing one (ties:
:func:`itk_nrreval.measures.confidence.tie_groups`). Re-exported by :mod:`itk_nrreval.evaluation`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from .confidence import Comparison, tie_groups

__all__ = ["higher_is_better", "ranks", "relative_ranks"]


def higher_is_better(measure: str) -> bool:
    """Overlap measures: higher is better; specificity and generalization: lower is better."""
    return measure.startswith("overlap")


def ranks(
    scores: Mapping[str, float],
    *,
    higher_is_better: bool,
    stderr: Mapping[str, float] | None = None,
    comparisons: Sequence[Comparison] = (),
) -> dict[str, int | None]:
    """Rank order (1 = best); tied scores share the better rank ("1, 2, 2, 4").

    Parameters
    ----------
    scores : dict of str to float
    higher_is_better : bool
    stderr, comparisons
        What tells scores apart from noise (:func:`tie_groups`); default: only equal scores
        are tied.

    Returns
    -------
    dict of str to int
        Same keys; NaN scores get None and do not take a rank.

    Examples
    --------
    >>> ranks({"a": 0.61, "b": 0.52, "c": 0.52, "d": 0.3}, higher_is_better=True)
    {'a': 1, 'b': 2, 'c': 2, 'd': 4}
    >>> ranks({"a": 0.61, "b": 0.60, "c": 0.3}, higher_is_better=True,
    ...       stderr={"a": 0.01, "b": 0.01, "c": 0.01})
    {'a': 1, 'b': 1, 'c': 3}
    """
    groups = tie_groups(
        scores, higher_is_better=higher_is_better, stderr=stderr, comparisons=comparisons
    )
    out: dict[str, int | None] = dict.fromkeys(scores)
    better = 0
    for group in groups:
        for k in group:
            out[k] = 1 + better
        better += len(group)
    return out


def relative_ranks(
    scores: Mapping[str, float],
    *,
    higher_is_better: bool,
    stderr: Mapping[str, float] | None = None,
    comparisons: Sequence[Comparison] = (),
) -> dict[str, float | None]:
    """Quantitative relative rank in percent: the best score 100, the worst 0, linear between.

    Scores not told apart from noise are tied (:func:`tie_groups`) and get one relative
    rank, that of their group's mean score, so a spread within the scores' errors is never
    stretched over the 0-100% range.

    Parameters
    ----------
    scores : dict of str to float
    higher_is_better : bool
    stderr : dict of str to float, optional
        Each score's standard error (e.g. the Monte-Carlo standard error of specificity).
    comparisons : sequence of Comparison
        This measure's pairwise comparisons with their subject-level intervals.

    Returns
    -------
    dict of str to float
        ``100 (g - worst) / (best - worst)`` with ``g`` the mean score of the registration's
        tie group and ``best``, ``worst`` those of the best and worst groups; 100 for all
        when every score is tied with the others (one group); None for NaN scores.

    Examples
    --------
    >>> relative_ranks({"fluid": 0.131, "mid": 0.249, "affine": 0.367}, higher_is_better=False)
    {'fluid': 100.0, 'mid': 50.0, 'affine': 0.0}
    >>> relative_ranks({"sitk": 0.13104, "itk": 0.13100}, higher_is_better=False,
    ...                stderr={"sitk": 0.0005, "itk": 0.0005})
    {'sitk': 100.0, 'itk': 100.0}
    """
    groups = tie_groups(
        scores, higher_is_better=higher_is_better, stderr=stderr, comparisons=comparisons
    )
    out: dict[str, float | None] = dict.fromkeys(scores)
    if not groups:
        return out
    means = [math.fsum(float(scores[k]) for k in g) / len(g) for g in groups]
    best, worst = means[0], means[-1]
    for group, g in zip(groups, means, strict=True):
        for k in group:
            if len(groups) == 1:
                out[k] = 100.0
            else:
                out[k] = round(100.0 * (g - worst) / (best - worst), 10) + 0.0  # no -0.0
    return out
