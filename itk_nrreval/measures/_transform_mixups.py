"""Transform mix-ups: flagged subjects' images resampled through changed transforms.

Two causes of a failed registration cannot be read off a transform alone: an **inverted
transform** (the subject's image through the inverse of its transform is much closer to the
model of the others) and **another subject's transform** (another flagged subject's image
fits it much better than its own: two subjects' transforms swapped or mixed up).
:func:`itk_nrreval.measures.subject_qc.transform_mixups` chooses the flagged subjects to check;
here are the alternatives resampled for them (:class:`Alternative`) and how much better the
best of them fits, with the cause it points to in words (:func:`better_fits`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ._subject_measures import AffineSpans

__all__ = ["Alternative", "MAX_MIXUP_SUBJECTS", "better_fits"]


@dataclass(frozen=True)
class Alternative:
    """One subject's image resampled through a changed transform, for a mix-up check.

    Attributes
    ----------
    image : int
        Whose image (manifest index).
    transform : int
        Through whose transform under the same registration (manifest index).
    inverse : bool
        Through the inverse of that transform.
    """

    image: int
    transform: int
    inverse: bool = False


#: At most this many flagged subjects (the farthest from the model first) are resampled
#: through changed transforms: k subjects cost k inversions and k (k - 1) resamplings.
MAX_MIXUP_SUBJECTS = 8


def better_fits(
    chosen: Sequence[int],
    *,
    row: Mapping[int, int],
    gram: np.ndarray,
    products: Callable[[Sequence[Alternative]], tuple[np.ndarray, np.ndarray]],
    images: Sequence[str],
) -> dict[int, tuple[float, str]]:
    """How much better the `chosen` subjects fit with their transform inverted or exchanged.

    Each chosen subject i's image is resampled through the inverse of its transform, and
    every other chosen subject j's image through i's transform (`products` gives their inner
    products). Each is measured as the leave-one-out score is -- its distance to the affine
    span of the scored subjects but i (and j) -- and compared with i's own resampled image's
    distance to the same span.

    Parameters
    ----------
    chosen : sequence of int
        The subjects to check (manifest indices), all in the scores.
    row : mapping of int to int
        Each scored subject's row of `gram` (manifest index -> row).
    gram : ndarray of shape (n, n)
        Gram matrix of the scored subjects' centred resampled images.
    products : callable
        As :func:`itk_nrreval.measures.subject_qc.transform_mixups`'s.
    images : sequence of str
        Every subject's image, as the manifest names it (named in the words).

    Returns
    -------
    dict of int to (float, str)
        Per subject checked: own distance / the best alternative's distance, and the cause
        that alternative points to, in words; empty when nothing is chosen.
    """
    alternatives = [Alternative(i, i, inverse=True) for i in chosen]
    alternatives += [Alternative(j, i) for i in chosen for j in chosen if j != i]
    if not alternatives:
        return {}
    cross, squared = products(alternatives)
    spans = AffineSpans(gram)
    best: dict[int, tuple[float, Alternative]] = {}
    for c, alt in enumerate(alternatives):
        i = alt.transform
        left_out = [row[alt.image], row[i]]
        own = spans.member_distance(row[i], left_out)
        changed = spans.distance(cross[c], float(squared[c]), left_out)
        ratio = own / changed if changed > 0 else math.inf
        if i not in best or ratio > best[i][0]:
            best[i] = (ratio, alt)
    return {i: (ratio, _cause(alt, ratio, images)) for i, (ratio, alt) in best.items()}


def _cause(alt: Alternative, ratio: float, images: Sequence[str]) -> str:
    """The cause an alternative fitting `ratio` times better points to, in words."""
    if alt.inverse:
        return (
            f"inverted transform: its inverse brings the image {ratio:.1f}x closer to the "
            "model of the others (a transform of the wrong direction: image to reference "
            "points?)"
        )
    j = alt.image
    return (
        f"its transform looks like another subject's: subject {j}'s image "
        f"({images[j]}) fits it {ratio:.1f}x better than its own (transforms swapped "
        "or mixed up?)"
    )
