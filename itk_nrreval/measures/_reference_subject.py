"""Which subject is a registration's reference, when one is: registered to itself.

A registration whose reference is one of the cohort's own images registers that subject to
itself: its transform says nothing about the registration, and subject quality control
(:mod:`itk_nrreval.measures.subject_qc`) reports it as the reference, never flags it, and leaves it
out of the cohort statistics. :func:`reference_subject` finds it from the manifest's
``reference_index``, or from an identity transform on the reference's own file or voxels.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

__all__ = ["IDENTITY_MM", "reference_subject"]

#: A subject whose transform moves the points of the grid by less than this RMS (mm) is
#: registered by the identity, for :func:`reference_subject`: a registration of an image to
#: itself returns the identity to round-off (a zero gradient everywhere: the optimizer
#: never moves), while a hundredth of a mm is a hundredth of the 1 mm voxels, the finest
#: here, and far below what any registration of two different images leaves.
IDENTITY_MM = 0.01


def reference_subject(
    reference: Any,
    images: Sequence[Any],
    *,
    reference_index: int | None = None,
    displacement_rms_mm: Sequence[float | None] | None = None,
) -> int | None:
    """Which subject is a registration's reference, if one is: registered to itself.

    Parameters
    ----------
    reference : path or InMemoryImage
        The registration's reference (:attr:`ManifestRegistration.reference
        <itk_nrreval.io.manifest.ManifestRegistration.reference>`).
    images : sequence of (path or InMemoryImage)
        The registered images, in manifest order (:attr:`Manifest.images
        <itk_nrreval.io.manifest.Manifest.images>`).
    reference_index : int, optional, keyword-only
        The manifest's ``reference_index``: it names the reference, whatever the transforms.
    displacement_rms_mm : sequence of float or None, optional, keyword-only
        Per subject, the RMS of ``|T(p) - p|`` over the evaluated voxels of the reference
        grid (mm; :class:`~itk_nrreval.io.plausibility.AffineFit`); None or NaN: not measured.

    Returns
    -------
    int or None
        `reference_index` when given; else the first subject whose transform is the
        identity (an RMS displacement of at most :data:`IDENTITY_MM`) and whose image is
        the reference: the same file, through any link or spelling, or the same voxels on
        the same grid (the content digest of :func:`itk_nrreval.io._cache.content_digest`,
        which the manifest's check has computed for the images already); else None.
    """
    if reference_index is not None:
        return int(reference_index)
    if displacement_rms_mm is None:
        return None
    # the identity first: only those subjects' files are compared (as a rule, none)
    still = [
        i for i, d in enumerate(displacement_rms_mm) if d is not None and d <= IDENTITY_MM
    ]  # NaN <= x is False: not measured is not the identity
    if not still:
        return None
    same_file = _file_identity(reference)
    if same_file is not None:
        for i in still:
            if _file_identity(images[i]) == same_file:
                return i
    digest = _content_digest(reference)
    if digest is None:
        return None  # nothing to compare: two digests not taken are not two equal images
    for i in still:
        if _content_digest(images[i]) == digest:
            return i
    return None


def _file_identity(item) -> tuple[int, int] | None:
    """(device, inode) of an image file, the same through links and spellings; None for an
    object in memory (or a file that cannot be read: then its digest says nothing either)."""
    if not isinstance(item, (str, os.PathLike)):
        return None
    try:
        stat = os.stat(item)
    except OSError:
        return None
    return stat.st_dev, stat.st_ino


def _content_digest(item) -> str | None:
    """The digest of the voxels and grid an image holds (a file's or an object's)."""
    if not isinstance(item, (str, os.PathLike)):
        return getattr(item, "content_digest", None)
    from ..io._cache import content_digest

    try:
        return content_digest(item)
    except (OSError, RuntimeError):
        return None
