"""Generalized Tanimoto overlap of a group of (fuzzy) label images (paper, Sections II-B, V-C).

The ground-truth reference measure: for N label images with memberships ``A[i, l, v]`` in
[0, 1] (image i, label l, voxel v),

        sum_{i<j} sum_l alpha_l sum_v min(A_il, A_jl)
    O = ---------------------------------------------
        sum_{i<j} sum_l alpha_l sum_v max(A_il, A_jl)

with the sums over all unordered pairs taken separately in numerator and denominator (never an
average of per-pair ratios). Crum, Camara & Hill, "Generalized overlap measures for evaluation
and validation in medical image analysis", IEEE TMI 25(11), 2006, eq. (4) without pair weights;
doi:10.1109/TMI.2006.880587.

Everything is read from one per-label table (:class:`OverlapTable`) built in one sweep over the
voxels: the pair sums of minima and maxima, the volumes and (when asked for) the boundary
complexity and the target-overlap sums. Every weighting, and the per-label Jaccard, Dice and
target overlap, come from that table. The sums are taken from the images in
:mod:`._overlap_sums`, by the kernels of :mod:`._overlap_kernels`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .._output import json_number
from ._overlap_sums import table_sums

__all__ = ["WEIGHTINGS", "OverlapTable", "overlap_table", "generalized_overlap"]

#: The label weightings, in the order reports list them.
WEIGHTINGS = (
    "volume",
    "inverse_volume",
    "inverse_volume_squared",
    "complexity",
    "inverse_volume_complexity",
)

_COMPLEXITY_WEIGHTINGS = ("complexity", "inverse_volume_complexity")


def _check_weighting(weighting: str) -> None:
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")


@dataclass(frozen=True)
class OverlapTable:
    """Per-label pair sums, volumes and complexities of a group of label images.

    Built once by :func:`overlap_table` (or from sums added up elsewhere, by
    :meth:`from_sums`); every scalar measure is read from it, so asking for all five
    weightings costs one pass over the voxels.

    Attributes
    ----------
    labels : ndarray of int, shape (n_labels,)
        The label values kept, ascending (for fuzzy input: the component indices).
    n_images : int
        N, the number of label images; there are N (N - 1) / 2 unordered pairs.
    pair_min, pair_max : ndarray of float, shape (n_labels,)
        ``sum_{i<j} sum_v min(A_il, A_jl)`` and the same with max, in voxels (memberships
        summed; exact integers for crisp input).
    volume : ndarray of float, shape (n_labels,)
        V_l, the mean over images of the label's volume ``sum_v A_il``, in mm^3 (voxel units
        when no spacing is known).
    complexity : ndarray of float, shape (n_labels,)
        The mean over the images that carry the label of ``sum_v |grad A_il| / sum_v A_il``,
        in mm^-1: boundary per unit volume. Zero for a label that fills the whole grid. All
        NaN when the table was built without it (``has_complexity`` false).
    target_overlap : ndarray of float, shape (n_labels,)
        Klein's target overlap ``|A_i ∩ A_j| / |A_j|`` averaged over the ordered pairs
        (i != j) whose target j carries the label (intersection as sum of minima). All NaN
        when the table was built without it (``has_target_overlap`` false).
    spacing : tuple of float
        Voxel size used for the gradients and volumes, mm, ITK order (x, y[, z]).
    fuzzy : bool
        True when the input was memberships rather than crisp label maps.
    skipped_labels : tuple of int
        Requested (or fuzzy) labels absent from every image, left out of every sum.
    has_complexity : bool
        Whether `complexity` was computed (``overlap_table(..., complexity=True)``); the
        complexity weightings need it.
    has_target_overlap : bool
        Whether `target_overlap` was computed (``overlap_table(..., target_overlap=True)``).
    """

    labels: np.ndarray
    n_images: int
    pair_min: np.ndarray
    pair_max: np.ndarray
    volume: np.ndarray
    complexity: np.ndarray
    target_overlap: np.ndarray
    spacing: tuple[float, ...]
    fuzzy: bool
    skipped_labels: tuple[int, ...] = field(default=())
    has_complexity: bool = True
    has_target_overlap: bool = True

    @classmethod
    def from_sums(
        cls,
        labels,
        volume,
        target_sums,
        gradient_sums,
        pair_min,
        pair_max,
        *,
        spacing: Sequence[float],
        fuzzy: bool,
        skipped_labels: Sequence[int] = (),
    ) -> OverlapTable:
        """The table from its per-image and per-label sums, in voxel units.

        For callers that add the sums up themselves (e.g. over blocks of voxels, with
        :func:`._overlap_kernels.membership_pair_sums`); :func:`overlap_table` ends here too.

        Parameters
        ----------
        labels : array_like of int, shape (n_labels,)
            The label values, ascending.
        volume : array_like of float, shape (n_images, n_labels)
            ``sum_v A_il`` per image and label, voxel units (inside the mask).
        target_sums : array_like of float, shape (n_images, n_labels), or None
            ``sum_v sum_{j != i} min(A_il, A_jl)``, voxel units. None: the target overlap is
            not computed (NaN, ``has_target_overlap`` false).
        gradient_sums : array_like of float, shape (n_images, n_labels), or None
            ``sum_v |grad A_il|``, mm^-1 x voxels. None: the complexity is not computed (NaN,
            ``has_complexity`` false; the complexity weightings then raise).
        pair_min, pair_max : array_like of float, shape (n_labels,)
            ``sum_{i<j} sum_v min(A_il, A_jl)`` and the same with max, voxel units.
        spacing : sequence of float
            Voxel size in mm, ITK order (x, y[, z]); volumes are scaled by its product.
        fuzzy : bool
            Whether the sums come from memberships rather than crisp label maps.
        skipped_labels : sequence of int
            Labels left out (absent from every image), for the record.

        Returns
        -------
        OverlapTable

        Raises
        ------
        ValueError
            Arrays of inconsistent shapes, or fewer than two images.

        Notes
        -----
        ``complexity_l`` is the mean of ``gradient_sums[i, l] / volume[i, l]`` over the images
        with ``volume[i, l] > 0``; ``target_overlap_l`` the mean of ``target_sums[i, l] /
        volume[i, l]`` over the same images, divided by N - 1.
        """
        values = np.asarray(labels).reshape(-1)
        # C order throughout: the sums over images below round the same for every caller
        vol = np.ascontiguousarray(volume, dtype=np.float64)
        p = np.asarray(pair_min, dtype=np.float64).reshape(-1)
        q = np.asarray(pair_max, dtype=np.float64).reshape(-1)
        n_labels = values.size
        if vol.ndim != 2 or vol.shape[1] != n_labels or p.size != n_labels or q.size != n_labels:
            raise ValueError(
                f"from_sums: labels {values.shape}, volume {vol.shape}, pair_min {p.shape} and "
                f"pair_max {q.shape} do not agree on (n_images, n_labels)"
            )
        n_images = vol.shape[0]
        if n_images < 2:
            raise ValueError(f"from_sums: need at least 2 images, got {n_images}")
        for name, arr in (("target_sums", target_sums), ("gradient_sums", gradient_sums)):
            if arr is not None and np.shape(arr) != vol.shape:
                raise ValueError(
                    f"from_sums: {name} has shape {np.shape(arr)}, expected {vol.shape}"
                )
        present = vol > 0  # (N, L)
        carriers = present.sum(0)
        denom = np.where(present, vol, 1.0)
        nan = np.full(n_labels, np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            if gradient_sums is None:
                complexity = nan
            else:
                gsum = np.ascontiguousarray(gradient_sums, dtype=np.float64)
                complexity = np.where(present, gsum / denom, 0.0).sum(0) / carriers
            if target_sums is None:
                target = nan.copy()
            else:
                s_pairs = np.ascontiguousarray(target_sums, dtype=np.float64)
                target = np.where(present, s_pairs / denom, 0.0).sum(0)
                target = target / (carriers * (n_images - 1))
        return cls(
            labels=values,
            n_images=n_images,
            pair_min=p,
            pair_max=q,
            volume=vol.mean(axis=0) * float(np.prod(spacing)),
            complexity=complexity,
            target_overlap=target,
            spacing=tuple(float(s) for s in spacing),
            fuzzy=bool(fuzzy),
            skipped_labels=tuple(int(v) for v in skipped_labels),
            has_complexity=gradient_sums is not None,
            has_target_overlap=target_sums is not None,
        )

    @property
    def jaccard(self) -> np.ndarray:
        """Group Jaccard (Tanimoto) per label, ``pair_min / pair_max``, shape (n_labels,)."""
        return self.pair_min / self.pair_max

    @property
    def dice(self) -> np.ndarray:
        """Group Dice per label, ``2 pair_min / (pair_min + pair_max)``, shape (n_labels,).

        Equal to ``2 J / (1 + J)``: the pair sums of ``A_i + A_j`` are min plus max.
        """
        return 2.0 * self.pair_min / (self.pair_min + self.pair_max)

    def weights(self, weighting: str = "inverse_volume") -> np.ndarray:
        """The label weights alpha_l, shape (n_labels,), unnormalized.

        Parameters
        ----------
        weighting : {"volume", "inverse_volume", "inverse_volume_squared", "complexity", \
"inverse_volume_complexity"}
            ``"volume"``: 1 (implicit volume weighting); ``"inverse_volume"``: 1 / V_l (mm^-3);
            ``"inverse_volume_squared"``: 1 / V_l^2; ``"complexity"``: the complexity C_l
            (mm^-1); ``"inverse_volume_complexity"``: C_l / V_l.

        Raises
        ------
        ValueError
            An unknown weighting, or a complexity weighting of a table built with
            ``complexity=False``.
        """
        _check_weighting(weighting)
        if weighting in _COMPLEXITY_WEIGHTINGS and not self.has_complexity:
            raise ValueError(
                f"weighting {weighting!r} needs the label complexities, but this table was "
                "built with complexity=False (no gradient sums); build it with "
                "overlap_table(..., complexity=True)"
            )
        if weighting == "volume":
            return np.ones_like(self.volume)
        if weighting == "inverse_volume":
            return 1.0 / self.volume
        if weighting == "inverse_volume_squared":
            return 1.0 / self.volume**2
        if weighting == "complexity":
            return self.complexity.copy()
        return self.complexity / self.volume

    def generalized(self, weighting: str = "inverse_volume") -> float:
        """The generalized overlap ``sum_l alpha_l pair_min_l / sum_l alpha_l pair_max_l``.

        In [0, 1]; 1 when every image carries every label on the same voxels. NaN (with a
        warning) when every weight is zero, e.g. complexity weighting of labels without
        boundary. `weighting` as in :meth:`weights` (which raises for a complexity weighting
        of a table built with ``complexity=False``).
        """
        alpha = self.weights(weighting)
        den = float(alpha @ self.pair_max)
        if not den > 0:
            warnings.warn(
                f"generalized overlap with weighting {weighting!r} is undefined: every label "
                "weight is zero",
                RuntimeWarning,
                stacklevel=2,
            )
            return math.nan
        return float(alpha @ self.pair_min) / den

    def to_dict(self) -> dict:
        """Plain-Python form: the generalized overlap per weighting and one row per label.

        JSON-ready: a value not computed (complexity or target overlap of a table built
        without them, and the weightings that need them) or undefined is None, never NaN.
        """
        generalized = {
            w: (
                None
                if w in _COMPLEXITY_WEIGHTINGS and not self.has_complexity
                else json_number(self.generalized(w))
            )
            for w in WEIGHTINGS
        }
        return {
            "n_images": self.n_images,
            "fuzzy": self.fuzzy,
            "spacing": list(self.spacing),
            "skipped_labels": [int(v) for v in self.skipped_labels],
            "generalized": generalized,
            "labels": [{k: json_number(v) for k, v in row.items()} for row in self.rows()],
        }

    def rows(self) -> list[dict]:
        """One dict per label: value, volume, complexity, Jaccard, Dice, target overlap, sums.

        Complexity and target overlap are NaN when the table was built without them.
        """
        jac, dice = self.jaccard, self.dice
        return [
            {
                "label": int(self.labels[k]),
                "volume": float(self.volume[k]),
                "complexity": float(self.complexity[k]),
                "jaccard": float(jac[k]),
                "dice": float(dice[k]),
                "target_overlap": float(self.target_overlap[k]),
                "pair_min": float(self.pair_min[k]),
                "pair_max": float(self.pair_max[k]),
            }
            for k in range(len(self.labels))
        ]


def generalized_overlap(
    labels,
    *,
    weighting: str = "inverse_volume",
    label_values=None,
    include_background: bool = False,
    mask=None,
    spacing=None,
) -> float:
    """Generalized Tanimoto overlap of a group of label images (Crum et al. 2006, eq. 4).

    ``overlap_table(labels, ...).generalized(weighting)``, computing only what `weighting`
    needs: the gradients only for the complexity weightings, never the target overlap. To
    read several weightings, build the table once with :func:`overlap_table`.

    Parameters
    ----------
    labels : ndarray or sequence of sitk.Image or paths
        See :func:`overlap_table`.
    weighting : {"volume", "inverse_volume", "inverse_volume_squared", "complexity", \
"inverse_volume_complexity"}
        The label weights alpha_l (see :meth:`OverlapTable.weights`). The paper's main choice
        is ``"inverse_volume"`` (every label counts equally, whatever its size).
    label_values, include_background, mask, spacing
        See :func:`overlap_table`.

    Returns
    -------
    float
        The overlap in [0, 1]; higher is better.

    Examples
    --------
    >>> import numpy as np, itk_nrreval as nr
    >>> a = np.array([[0, 1, 1, 0], [0, 0, 1, 1]])
    >>> nr.generalized_overlap(a)  # |{2}| / |{1, 2, 3}|
    0.3333333333333333
    """
    _check_weighting(weighting)
    table = overlap_table(
        labels,
        label_values=label_values,
        include_background=include_background,
        mask=mask,
        spacing=spacing,
        complexity=weighting in _COMPLEXITY_WEIGHTINGS,
        target_overlap=False,
    )
    return table.generalized(weighting)


def overlap_table(
    labels,
    *,
    label_values=None,
    include_background: bool = False,
    mask=None,
    spacing=None,
    complexity: bool = True,
    target_overlap: bool = True,
    progress: bool = True,
) -> OverlapTable:
    """The per-label pair sums, volumes and complexities of N label images, in one pass.

    Parameters
    ----------
    labels : ndarray or sequence of sitk.Image or paths
        N >= 2 label images on one grid, as one of

        - an integer (or bool) array of shape (n_images, *spatial): crisp label maps;
        - a floating array of shape (n_images, n_components, *spatial): fuzzy memberships in
          [0, 1], component k being the membership of label k;
        - a sequence of scalar SimpleITK images or files: crisp label maps (a floating pixel
          type is accepted when every value is an integer);
        - a sequence of multi-component images or files (one per subject, components as
          above): fuzzy memberships;
        - a sequence of membership files that name their labels (a JSON sidecar or header
          from :func:`itk_nrreval.io._membership_files.write_membership_image`, as written by
          ``nrreval evaluate --save-resampled``): component k is the membership of the label
          the file names for it, and there is no background component. One label may come
          as a scalar image.

        The dtype of a bare array decides: crisp label maps must have an integer dtype.
    label_values : sequence of int, optional
        The labels to evaluate. Default: every value present in any image (crisp), or every
        component with a nonzero membership somewhere (fuzzy), less background 0 unless
        `include_background`. When given, they are used as given (`include_background` has
        no effect); fuzzy label values must be component indices, unless the files name
        their labels. Values absent from every image are skipped with a warning.
    include_background : bool
        Keep label 0 (component 0 for fuzzy input) in the default label set. An error for
        files that name their labels without a background one.
    mask : ndarray of bool of shape (*spatial), sitk.Image, path, or None
        Sum only over voxels inside the mask. Gradients are still taken on the full grid.
    spacing : sequence of float, optional
        Voxel size in mm, ITK order (x, y[, z]) -- the reverse of the numpy axes -- for bare
        arrays only (images bring their own; passing both is an error). Default 1 along every
        axis. Only the complexity weights depend on it.
    complexity : bool
        Compute the label complexities (gradient sums), which the ``"complexity"`` and
        ``"inverse_volume_complexity"`` weightings need. False skips the gradients (most of
        the work for crisp maps): the table's `complexity` is NaN and those weightings raise.
    target_overlap : bool
        Compute the per-label target overlap (a second pass over the counts for crisp maps).
        False leaves the table's `target_overlap` NaN.
    progress : bool
        A progress bar on stderr over the labels of large fuzzy inputs (crisp maps take one
        pass and show none).

    Returns
    -------
    OverlapTable

    Raises
    ------
    InputError
        Fewer than two images, images on different grids, non-integer values in a crisp label
        map, memberships outside [0, 1], a mixture of scalar and multi-component images, files
        that name different labels (or some that name theirs and some that do not), or no
        label to evaluate.
    ValueError
        Bad `spacing` or `label_values`.

    Notes
    -----
    With ``p_l = sum_{i<j} sum_v min(A_il, A_jl)`` and ``q_l`` the same with max, the
    generalized overlap is ``sum_l alpha_l p_l / sum_l alpha_l q_l``; per label,
    Jaccard ``p_l / q_l`` and Dice ``2 p_l / (p_l + q_l)``. Limit cases: two images and one
    label give the plain Jaccard index; identical images give 1; disjoint labels give 0.

    The pair sums avoid the O(N^2 n) loop over pairs: O(N n) in all, in one sweep over the
    voxels (:mod:`itk_nrreval.measures._overlap_sums` says how, and how the complexity is taken).

    Paper, Sections II-B and V-C; Crum, Camara & Hill, IEEE TMI 25(11):1451-1461, 2006, eq. (4)
    without pair weights. Target overlap: Klein et al., NeuroImage 46(3), 2009.
    """
    sums = table_sums(
        labels,
        label_values=label_values,
        include_background=include_background,
        mask=mask,
        spacing=spacing,
        complexity=complexity,
        target_overlap=target_overlap,
        progress=progress,
    )
    if sums.skipped_labels:
        warnings.warn(
            f"labels {list(sums.skipped_labels)} are absent from every image and are skipped",
            UserWarning,
            stacklevel=2,
        )
    return OverlapTable.from_sums(
        sums.labels,
        sums.volume,
        sums.target_sums,
        sums.gradient_sums,
        sums.pair_min,
        sums.pair_max,
        spacing=sums.spacing,
        fuzzy=sums.fuzzy,
        skipped_labels=sums.skipped_labels,
    )
