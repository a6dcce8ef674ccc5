"""The numbers subject quality control judges a subject by (:mod:`itk_nrreval.measures.subject_qc`).

All of them come from what the evaluation has already computed, nothing is resampled again:

* distances between the subjects' resampled images, from their Gram matrix alone: each
  one's leave-one-out distance to the texture model of the others
  (:func:`leave_one_out_distances`), the pairwise distances (:func:`pair_distances`), and the
  distance of any image to the affine span of the subjects but a few left out
  (:class:`AffineSpans`, which the transform mix-up checks query too);
* each subject's label overlap with the others, from the per-image overlap sums
  (:func:`subject_overlaps`);
* each subject's bias-corrected distance: the distance of its bias-corrected image
  (:func:`bias_corrected`) to the mean of the others' (:func:`others_mean_distances`), from
  sums the pipeline takes block by block;
* robust z-scores over the cohort (:func:`robust_z`), and the concern that ranks the subjects:
  the weighted mean of their signed z-scores (:data:`CONCERN_TERMS`, :func:`concern_scores`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
from scipy import ndimage

__all__ = [
    "MAD_TO_SD",
    "robust_z",
    "BIAS_SCALE_MM",
    "bias_corrected",
    "others_mean_distances",
    "leave_one_out_distances",
    "pair_distances",
    "subject_overlaps",
    "AffineSpans",
    "ConcernTerm",
    "CONCERN_TERMS",
    "concern_scores",
    "subject_concern",
]

#: The MAD of a normal sample times this estimates its standard deviation.
MAD_TO_SD = 1.4826


def robust_z(
    values,
    *,
    log: bool = False,
    floor: float = 0.0,
    least_spread: float = 0.0,
    among: np.ndarray | Sequence[bool] | None = None,
) -> np.ndarray:
    """Robust z-scores over a cohort: ``(x - median) / max(1.4826 MAD, least spread)``.

    Parameters
    ----------
    values : array_like of float, shape (n,)
        One value per subject; NaN values get NaN and are left out of the median and MAD.
    log : bool
        Score ``log(max(x, floor))`` instead of x (for positive, scale-like measures).
    floor : float
        With `log`, values below it are taken as it (must then be > 0).
    least_spread : float
        The least spread, in the units of `values`, the z-scores are taken over: the scale
        is at least this (linear) or, with `log`, at least ``log(1 + least_spread / m)``,
        ``m`` the median (in the units of `values`) or `least_spread` if larger -- the log
        distance from the median to a value `least_spread` above it, at most ``log 2``.
    among : array_like of bool, shape (n,), optional
        The values the median and MAD are taken over (default: every one); every value
        gets its z against them (a registration's reference is scored against the others).

    Returns
    -------
    ndarray of float, shape (n,)
        Finite for finite values when `least_spread` > 0. With `least_spread` 0 and a MAD of
        0 (over half of the cohort share one value), values at the median score 0 and any
        other +-inf: a cohort that does not vary at all makes any departure from it extreme.
    """
    x = np.asarray(values, np.float64).copy()
    if log:
        x = np.log(np.maximum(x, floor))  # NaN stays NaN
    ok = np.isfinite(x)
    z = np.full(x.shape, np.nan)
    cohort = ok if among is None else ok & np.asarray(among, bool)
    if not cohort.any():
        return z
    median = float(np.median(x[cohort]))
    scale = MAD_TO_SD * float(np.median(np.abs(x[cohort] - median)))
    if least_spread > 0:
        if log:
            at = max(math.exp(median), least_spread)
            scale = max(scale, math.log1p(least_spread / at))
        else:
            scale = max(scale, least_spread)
    if scale > 0:
        z[ok] = (x[ok] - median) / scale
    else:
        diff = x[ok] - median
        z[ok] = np.where(diff == 0, 0.0, np.copysign(np.inf, diff))
    return z


#: The standard deviation (mm) of the Gaussian local mean an image is divided by in
#: :func:`bias_corrected`: coarse enough that anatomy a few millimetres across stays, fine
#: enough to follow a smooth bias field. Chosen on the tuning split of the genuine
#: registrations (issue 42): 5, 10 and 20 mm tracked the true error alike (0.83-0.85).
BIAS_SCALE_MM = 10.0


def bias_corrected(
    image: np.ndarray,
    region: np.ndarray,
    *,
    spacing: Sequence[float],
    scale_mm: float = BIAS_SCALE_MM,
) -> np.ndarray:
    """An image divided by its local mean: its gain and smooth multiplicative bias taken away.

    Two subjects' images differ by more than misregistration: a scanner gain, a bias field,
    noise. The first two dominate the distance between raw intensities (issue 42: the model
    distance tracked the true error at 0.57 on the tuning split; this at 0.84), and
    dividing by a local mean removes both while leaving the edges and structures that
    misregistration moves.

    Parameters
    ----------
    image : ndarray of float, shape (*spatial_zyx,)
        An image on the common grid (numpy's axis order: z first).
    region : ndarray of bool, the same shape
        The voxels it is judged on (the evaluation region, where the image covers it): the
        local mean is taken over these alone (normalised convolution), so the background
        and voxels outside the image's field of view do not pull it down.
    spacing : sequence of float, length ``image.ndim``
        The grid's voxel spacing in ITK's order (x, y[, z]), mm. The Gaussian is isotropic
        in physical space: the grid's axes are orthogonal whatever its direction cosines.
    scale_mm : float
        The Gaussian's standard deviation, mm.

    Returns
    -------
    ndarray of float32, the same shape
        ``x / m`` inside `region`, with ``m = G * (x 1_R) / G * 1_R`` (Gaussian-weighted
        means over the region); 0 outside it and where ``m`` is not above ``1e-6`` of its
        largest magnitude (for positive, MR-like intensities: a local mean near 0 says no
        signal to compare).
    """
    # float32, as the images are cached: half the time of float64 (about 1 s for a 1 mm
    # brain), at a relative error of 1e-6
    x = np.asarray(image, np.float32)
    inside = np.asarray(region, bool)
    if x.shape != inside.shape:
        raise ValueError(f"image shape {x.shape} and region shape {inside.shape} differ")
    sigma = scale_mm / np.asarray(spacing, np.float64)[::-1]  # per numpy axis
    weight = ndimage.gaussian_filter(inside.astype(np.float32), sigma, mode="constant")
    local = ndimage.gaussian_filter(np.where(inside, x, np.float32(0)), sigma, mode="constant")
    with np.errstate(divide="ignore", invalid="ignore"):
        local = np.where(inside, local / weight, 0.0)
    floor = 1e-6 * float(np.max(np.abs(local), initial=0.0))
    ok = inside & (local > floor)
    out = np.zeros_like(x)
    out[ok] = x[ok] / local[ok]
    return out


def others_mean_distances(centred_squares: np.ndarray) -> np.ndarray:
    """Each subject's Euclidean distance to the mean of the others, from its sum of squares.

    Parameters
    ----------
    centred_squares : ndarray of shape (n,)
        Per subject k, ``sum_v (h_k(v) - hbar(v))^2`` over the region's voxels, where ``hbar``
        is the mean of all n subjects' (bias-corrected) images: what the pipeline adds up
        block by block.

    Returns
    -------
    ndarray of shape (n,)
        ``|h_k - mean_{j != k} h_j|``: as ``h_k - mean_{j != k} h_j = n / (n - 1) (h_k -
        hbar)``, it is ``n / (n - 1) sqrt(centred_squares[k])`` (intensity ratio units).
    """
    squares = np.asarray(centred_squares, np.float64)
    n = squares.shape[0]
    if n < 2:
        return np.full(n, np.nan)
    return n / (n - 1) * np.sqrt(np.maximum(squares, 0.0))


def leave_one_out_distances(gram: np.ndarray) -> np.ndarray:
    """Each image's distance to the texture model of the others, from their Gram matrix.

    Parameters
    ----------
    gram : ndarray of shape (n, n)
        Gram matrix of the centred images (:meth:`TextureModel.from_gram`), n >= 4.

    Returns
    -------
    ndarray of shape (n,)
        Image k's Euclidean distance (intensity units) to its reconstruction by the model
        of the n - 1 others with all their modes: its distance to their affine span
        (:func:`itk_nrreval.measures.specificity.loo_generalization`).
    """
    gram = np.asarray(gram, dtype=float)
    n = gram.shape[0]
    centring = np.eye(n) - 1.0 / n
    values, vectors = np.linalg.eigh(centring @ gram @ centring)
    # n points span at most n - 1 dimensions: the centred Gram matrix has one zero
    # eigenvalue, and n - 1 positive ones where the points are affinely independent
    kept = values[1:]
    if kept[0] <= kept[-1] * n * 1e-12:
        # a duplicate or a degenerate cohort: the images in an affine dependency are at
        # distance 0 (refitting each model instead cost n SVDs, O(n^4): half an hour or more at
        # n = 1,000)
        spans = AffineSpans(gram)
        return np.array([spans.member_distance(k, [k]) for k in range(n)])
    # the distance from point k to the affine span of the others is 1 / sqrt(G+_kk), G+ the
    # pseudo-inverse of the centred Gram matrix: one eigendecomposition for all k, where
    # refitting n models costs n of them
    inverse_diagonal = np.einsum("ij,j,ij->i", vectors[:, 1:], 1.0 / kept, vectors[:, 1:])
    return 1.0 / np.sqrt(inverse_diagonal)


def pair_distances(gram: np.ndarray) -> np.ndarray:
    """The Euclidean distances between the images, shape (n, n), from their Gram matrix.

    ``|x_i - x_j|^2 = G_ii + G_jj - 2 G_ij`` (centring moves every image alike); round-off
    below zero is taken as 0.
    """
    g = np.asarray(gram, np.float64)
    diag = np.diag(g)
    return np.sqrt(np.maximum(diag[:, None] + diag[None, :] - 2 * g, 0.0))


def subject_overlaps(volume, target_sums, weights) -> np.ndarray:
    """Each subject's generalized overlap with the others, from the per-image sums.

    Parameters
    ----------
    volume, target_sums : array_like, shape (n, n_labels)
        ``sum_v A_il`` and ``sum_v sum_{j != i} min(A_il, A_jl)`` (voxel units), as
        :meth:`itk_nrreval.measures.overlap.OverlapTable.from_sums` takes them.
    weights : array_like, shape (n_labels,)
        The label weights alpha_l (e.g. the cohort table's inverse-volume weights).

    Returns
    -------
    ndarray of shape (n,)
        ``sum_l alpha_l sum_{j != i} min(A_il, A_jl) / sum_l alpha_l sum_{j != i} max(A_il,
        A_jl)``: the generalized Tanimoto overlap of the N - 1 pairs (i, j), where
        ``sum_{j != i} max = (N - 2) vol_i + sum_j vol_j - target_sums_i``
        (``max(a, b) = a + b - min(a, b)``). NaN where the denominator is 0.
    """
    vol = np.asarray(volume, np.float64)
    mins = np.asarray(target_sums, np.float64)
    alpha = np.asarray(weights, np.float64)
    n = vol.shape[0]
    maxs = (n - 2) * vol + vol.sum(axis=0) - mins
    num, den = mins @ alpha, maxs @ alpha
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


class AffineSpans:
    """Distances to the affine span of n images but a few left out, from their Gram matrix.

    One eigendecomposition of the centred Gram matrix serves every query; refitting the
    model of the remaining images for each query cost one per query (O(n^3) each, minutes
    for 64 queries at n = 1,000).

    Parameters
    ----------
    gram : ndarray of shape (n, n)
        Gram matrix of the images (squared intensity units); centred here on their mean
        (affine spans do not move with it).

    Notes
    -----
    With ``Gc = V L V^T`` the centred Gram matrix (the eigenvalues above ``n 1e-12`` times
    the largest kept), ``Gc^+`` its pseudo-inverse and ``c`` a vector's centred inner
    products with the images, the vector's squared distance to the span of all n images is
    ``|a|^2 - c^T Gc^+ c`` (the part outside it), and leaving out the images R adds
    ``b^T (Gc^+_RR)^-1 b`` with ``b = (Gc^+ c)_R + 1/n``: its component along the
    normals, within the span of all, of the span of the others (``(Gc^+)_k.`` is image k's
    dual vector, orthogonal to every other image's offset). For c = image k's own inner
    products and R = {k} this is ``1 / Gc^+_kk``, the leave-one-out distance. An affine
    dependency among the images (a duplicate) that involves left-out images keeps their
    directions in the span of the others: only the combinations of R's normals that no
    dependency involves count.
    """

    def __init__(self, gram: np.ndarray):
        g = np.asarray(gram, np.float64)
        self.n = n = g.shape[0]
        self._row_means = g.mean(axis=0)
        self._mean = float(self._row_means.mean())
        centred = g - self._row_means[:, None] - self._row_means[None, :] + self._mean
        self._centred = centred
        values, vectors = np.linalg.eigh(centred)
        kept = values > values[-1] * n * 1e-12
        self._pinv = (vectors[:, kept] / values[kept]) @ vectors[:, kept].T
        # the affine dependencies: the dropped directions but the constant one (the centring)
        dropped = vectors[:, ~kept] - vectors[:, ~kept].mean(axis=0)
        basis, weights, _ = np.linalg.svd(dropped, full_matrices=False)
        self._dependencies = basis[:, weights > 0.5]

    def distance(self, cross: np.ndarray, squared: float, left_out: Sequence[int]) -> float:
        """The distance (intensity units) of one more image to the affine span of the
        images but rows `left_out`, from its inner products with them `cross` (n,) and with
        itself `squared` (in the Gram matrix's centring)."""
        c = np.asarray(cross, np.float64)
        c_mean = float(c.mean())
        c = c - c_mean - self._row_means + self._mean
        own = squared - 2 * c_mean + self._mean
        dual = self._pinv @ c
        outside = max(own - float(c @ dual), 0.0)  # round-off below 0: in the span
        return self._distance(dual, outside, left_out)

    def member_distance(self, k: int, left_out: Sequence[int]) -> float:
        """The distance (intensity units) of image (row) `k` to the affine span of the
        images but rows `left_out` (which may hold k)."""
        # it lies in the span of all images: nothing outside it (|a|^2 - c^T Gc^+ c would
        # leave round-off whose square root is 1e-8 |a|)
        return self._distance(self._pinv @ self._centred[:, k], 0.0, left_out)

    def _distance(self, dual: np.ndarray, outside: float, left_out: Sequence[int]) -> float:
        rows = sorted(set(left_out))
        # combinations of the left-out images' normals that no affine dependency involves
        normals = np.eye(len(rows))
        if self._dependencies.shape[1]:
            u, s, _ = np.linalg.svd(self._dependencies[rows], full_matrices=True)
            normals = u[:, int(np.sum(s > 1e-6)) :]
        if not normals.shape[1]:
            return math.sqrt(outside)
        along = normals.T @ (dual[rows] + 1.0 / self.n)
        metric = normals.T @ self._pinv[np.ix_(rows, rows)] @ normals
        return math.sqrt(outside + max(float(along @ np.linalg.solve(metric, along)), 0.0))


class ConcernTerm(NamedTuple):
    """One term of :attr:`~itk_nrreval.measures.subject_qc.SubjectQC.concern`
    (:data:`CONCERN_TERMS`)."""

    #: The term in words (:attr:`~itk_nrreval.measures.subject_qc.SubjectQC.concern_from`).
    words: str
    #: Where its z-score is: :func:`concern_scores`'s key.
    key: str
    #: +1 where a larger value is worse, -1 for the overlap, where a smaller one is.
    sign: float
    #: Its weight in the mean.
    weight: float
    #: Only above zero counts (a term below zero counts as zero).
    worse_only: bool


#: The terms of :attr:`~itk_nrreval.measures.subject_qc.SubjectQC.concern` (:func:`concern_scores`).
#: Chosen on the tuning split of the genuine registrations alone (issue 42:
#: ``benchmarks/bench_subject_qc_genuine.py``, ``docs/subject-qc.md``), among the largest of
#: the five signed z-scores (the concern before), the overlap z alone, the model-distance z
#: alone, and means of the model-distance and overlap z with the deformation z-scores added
#: or not (counted above zero only or not) and overlap weights of 1, 2 and 3: with labels
#: 0.80 (second scan 0.82) Spearman with the true error, mean over the deformable
#: registrations, without 0.63 (0.65). Then (issue 42, fifth session, again on tuning
#: alone, declared before the other splits were measured) the model distance gave its
#: place to the distance between bias-corrected images (:func:`bias_corrected`),
#: weights unchanged: with labels 0.84, without 0.83.
CONCERN_TERMS = (
    ConcernTerm("overlap", "overlap_z", -1.0, 3.0, False),
    ConcernTerm("bias-corrected distance", "corrected_z", 1.0, 1.0, False),
    ConcernTerm("SDlogJ", "sdlogj_z", 1.0, 1.0, True),
    ConcernTerm("inverse consistency", "inverse_consistency_z", 1.0, 1.0, True),
)


def concern_scores(z_scores: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The subjects' concern: the weighted mean of their signed z-scores.

    Parameters
    ----------
    z_scores : mapping of str to array_like of shape (n,)
        Per key of :data:`CONCERN_TERMS` (``overlap_z``, ``corrected_z``, ``sdlogj_z``,
        ``inverse_consistency_z``), the subjects' robust z-scores as
        :func:`~itk_nrreval.measures.subject_qc.assess_subjects` computes them (unsigned); NaN, or a
        key left out, where a term was not measured.

    Returns
    -------
    concern : ndarray of shape (n,)
        Per subject, ``sum_k w_k t_k / sum_k w_k`` over the terms ``k`` measured, with
        ``t_k`` the z-score times the term's sign, taken as ``max(t_k, 0)`` for a
        `worse_only` term, and ``w_k`` its weight; NaN where no term was measured.
    largest : ndarray of int, shape (n,)
        Per subject, the index into :data:`CONCERN_TERMS` of the term contributing most
        (the largest ``w_k t_k``; the first such term in a tie); -1 where no term was
        measured.
    """
    columns = [np.atleast_1d(np.asarray(v, np.float64)) for v in z_scores.values()]
    n = max((len(c) for c in columns), default=0)
    weighted = np.full((len(CONCERN_TERMS), n), -np.inf)
    weights = np.zeros((len(CONCERN_TERMS), n))
    for k, term in enumerate(CONCERN_TERMS):
        values = z_scores.get(term.key)
        if values is None:
            continue
        signed = term.sign * np.broadcast_to(np.asarray(values, np.float64), (n,))
        if term.worse_only:
            signed = np.maximum(signed, 0.0)  # NaN stays NaN
        measured = ~np.isnan(signed)
        weighted[k, measured] = term.weight * signed[measured]
        weights[k, measured] = term.weight
    total = weights.sum(axis=0)
    found = total > 0
    concern = np.full(n, np.nan)
    concern[found] = np.where(weights > 0, weighted, 0.0).sum(axis=0)[found] / total[found]
    largest = np.where(found, np.argmax(weighted, axis=0), -1)
    return concern, largest


def subject_concern(values: Mapping[str, float | None]) -> tuple[float | None, str | None]:
    """One subject's concern (:func:`concern_scores`) and the term contributing most, in
    words; (None, None) when none was measured."""
    z_scores = {
        t.key: math.nan if values.get(t.key) is None else float(values[t.key])
        for t in CONCERN_TERMS
    }
    concern, largest = concern_scores(z_scores)
    if largest[0] < 0:
        return None, None
    return float(concern[0]), CONCERN_TERMS[int(largest[0])].words
