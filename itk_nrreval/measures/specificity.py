"""Specificity and generalization of a shape-free texture model (paper, Section III).

Specificity (paper eq. 4-5): draw M samples y from the model, and average the distance from
each to its nearest training image, raised to the power lambda::

    S = 1/M sum_mu min_i |x_i - y_mu|^lambda,      stderr = STD_mu / sqrt(M - 1)

Lower is better: a model built from a good registration generates images close to the
training set. Generalization swaps the roles of the training set and the sample set
(1/N sum_i min_mu |x_i - y_mu|^lambda, stderr STD_i / sqrt(N - 1)).

All distances are computed in the space of non-normalized texture parameters, where L2
distances equal image-space L2 distances exactly (every non-zero mode is kept).

With ``groups`` (issue 19, the paper's closing discussion of multi-modal groups) the model is
a Gaussian mixture, one Gaussian per group (:class:`itk_nrreval.measures.model.MixtureModel`), and
the samples are stratified by group: group g gets ``M_g`` samples, M split in proportion to
the mixture weights ``N_g / N`` (largest remainders), and

    S = sum_g (N_g / N) S_g,        stderr^2 = sum_g (N_g / N)^2 stderr_g^2,

where ``S_g`` and ``stderr_g`` are the formulas above over group g's samples, each measured
to the nearest of *all* N training images, in the joint parameter space of the N images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .._errors import InputError, readable
from . import _search
from .model import MixtureModel, TextureModel

__all__ = [
    "MixtureSummary",
    "SpecificityResult",
    "GeneralizationResult",
    "SpecificityComparison",
    "specificity",
    "generalization",
    "texture_measures",
    "compare_specificity",
    "loo_generalization",
    "MAX_SEED",
]

_DISTANCES = ("l1", "l2")
# From this many training images on, the blocked search serves "auto" and "cpu". The search's
# own dict, not a copy: tests and benchmarks set its entries here to force either path.
_BLOCKED_MIN_IMAGES = _search.BLOCKED_MIN_IMAGES


@dataclass(frozen=True)
class MixtureSummary:
    """The groups of a mixture model's specificity (``groups=`` given).

    Attributes
    ----------
    groups : tuple of hashable
        The group labels, in order of first appearance among the images.
    sizes : ndarray of int, shape (n_groups,)
        N_g, the training images of each group.
    n_modes : ndarray of int, shape (n_groups,)
        Modes of each group's Gaussian (N_g - 1 for generic data).
    weights : ndarray of shape (n_groups,)
        The mixture weights ``N_g / N``.
    n_samples : ndarray of int, shape (n_groups,)
        M_g, the samples drawn from each group's Gaussian (M split in proportion to the
        weights, largest remainders first; they sum to M).
    values, stderrs : ndarray of shape (n_groups,)
        Each group's specificity: the mean over its M_g samples of the distance to the
        nearest of *all* N training images, to the power ``exponent``, and
        ``STD / sqrt(M_g - 1)``.
    nearest_counts : ndarray of int, shape (n_groups, n_groups)
        ``[g, h]``: how many samples of group g have their nearest training image in group h.
        Row g sums to ``n_samples[g]``; the whole matrix to M.
    """

    groups: tuple
    sizes: np.ndarray
    n_modes: np.ndarray
    weights: np.ndarray
    n_samples: np.ndarray
    values: np.ndarray
    stderrs: np.ndarray
    nearest_counts: np.ndarray

    def to_dict(self) -> dict:
        return {
            "groups": [_json_label(g) for g in self.groups],
            "sizes": [int(v) for v in self.sizes],
            "n_modes": [int(v) for v in self.n_modes],
            "weights": [float(v) for v in self.weights],
            "n_samples": [int(v) for v in self.n_samples],
            "values": [float(v) for v in self.values],
            "stderrs": [float(v) for v in self.stderrs],
            "nearest_counts": [[int(c) for c in row] for row in self.nearest_counts],
        }


def _json_label(label):
    return label if isinstance(label, (str, int, float, bool)) or label is None else str(label)


@dataclass(frozen=True)
class SpecificityResult:
    """Specificity of one texture model.

    Attributes
    ----------
    value : float
        Mean over samples of the nearest-training distance to the power ``exponent``
        (image intensity units ** exponent; L1 sums over modes). Lower is better. For a
        mixture, the weighted mean ``sum_g (N_g / N) mixture.values[g]``.
    stderr : float
        ``STD / sqrt(M - 1)`` over the M per-sample values (paper, Section III-A). For a
        mixture, ``sqrt(sum_g (N_g / N)^2 mixture.stderrs[g]^2)`` (stratified sampling).
    n_samples, n_images, n_modes : int
        M, N and the number of modes kept (N - 1 for generic data); for a mixture, the
        modes of the joint parameter space of all N images, where distances are taken.
    nearest_counts : ndarray of int, shape (n_images,)
        How many samples fall in each training image's Voronoi cell (paper, Table 1).
    mixture : MixtureSummary or None
        The per-group numbers when ``groups`` was given; None for a single Gaussian.
    """

    value: float
    stderr: float
    n_samples: int
    n_images: int
    n_modes: int
    distance: str
    exponent: float
    seed: int
    nearest_counts: np.ndarray = field(repr=False)
    mixture: MixtureSummary | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["nearest_counts"] = [int(c) for c in self.nearest_counts]
        if self.mixture is None:
            del d["mixture"]
        else:
            d["mixture"] = self.mixture.to_dict()
        return d


@dataclass(frozen=True)
class GeneralizationResult:
    """Generalization of one texture model (the converse of specificity).

    Attributes
    ----------
    value, stderr : float
        Mean over training images of the distance to the nearest sample, to the power
        ``exponent``, and ``STD / sqrt(N - 1)``. Lower is better.
    nearest_distances : ndarray of shape (n_images,)
        Each training image's value.
    groups : tuple of hashable or None
        For a mixture model, its group labels (samples from every group count); else None.
    """

    value: float
    stderr: float
    n_samples: int
    n_images: int
    distance: str
    exponent: float
    seed: int
    nearest_distances: np.ndarray = field(repr=False)
    groups: tuple | None = None

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["nearest_distances"] = [float(v) for v in self.nearest_distances]
        if self.groups is None:
            del d["groups"]
        else:
            d["groups"] = [_json_label(g) for g in self.groups]
        return d


@dataclass(frozen=True)
class SpecificityComparison:
    """Specificity of two registrations of one image set on common random numbers.

    ``difference = a.value - b.value`` with ``difference_stderr`` from the per-sample paired
    differences: much smaller than combining ``a.stderr`` and ``b.stderr`` when the two
    models are alike. A negative difference means `a` is the more specific (better). For
    mixtures, both are the weighted sums over groups of the per-group paired differences.
    """

    a: SpecificityResult
    b: SpecificityResult
    difference: float
    difference_stderr: float


MAX_SEED = 2**63
"""Seeds are integers in ``[0, MAX_SEED)``: the sampler mixes a seed into a 64-bit stream key
(:func:`itk_nrreval.measures._search.sampling.stream_key`)."""


def _checked_seed(seed, *, name: str = "seed") -> int:
    """`seed` as a Python int, or an :class:`InputError` naming parameter `name`.

    The one check of a seed: an integer (Python or numpy, not a bool) in ``[0, 2**63)``. A
    string, a float or a bool is refused rather than converted: ``int("abc")`` fails with a
    message that names no parameter, and ``int(1.5)`` would quietly run seed 1.

    Raises
    ------
    InputError
        "seed must be an integer in [0, 2**63), got 'abc'".
    """
    if (
        isinstance(seed, (bool, np.bool_))
        or not isinstance(seed, (int, np.integer))
        or not 0 <= seed < MAX_SEED
    ):
        raise InputError(f"{name} must be an integer in [0, 2**63), got {readable(seed)}")
    return int(seed)


def _check_options(n_samples: int, distance: str, exponent: float, seed) -> int:
    """Check the options; return the seed as an int (:func:`_checked_seed`)."""
    if distance not in _DISTANCES:
        raise ValueError(f"distance must be one of {_DISTANCES}, got {distance!r}")
    if not (
        isinstance(n_samples, (int, np.integer)) and 2 <= n_samples < _search.sampling.MAX_SAMPLES
    ):
        raise ValueError(f"n_samples must be an integer in [2, 2**36), got {readable(n_samples)}")
    if not (exponent > 0 and math.isfinite(exponent)):
        raise ValueError(f"exponent must be a positive number, got {readable(exponent)}")
    return _checked_seed(seed)


def _model(images, mask) -> TextureModel:
    if isinstance(images, (TextureModel, MixtureModel)):
        if mask is not None:
            raise ValueError("mask applies when fitting; pass it to TextureModel.from_images")
        return images
    return TextureModel.from_images(images, mask=mask)


def _fit(images, mask, groups) -> TextureModel | MixtureModel:
    """The model: a TextureModel when `groups` is None, else a MixtureModel."""
    model = _model(images, mask)
    if groups is None:
        return model
    if isinstance(model, MixtureModel):
        raise ValueError("groups: a MixtureModel carries its groups already; pass groups=None")
    return MixtureModel.from_model(model, groups)


def _joint(model: TextureModel | MixtureModel) -> TextureModel:
    return model.joint if isinstance(model, MixtureModel) else model


def _allocate(n_samples: int, mix: MixtureModel) -> np.ndarray:
    """M_g: M split in proportion to N_g (largest remainders; ties to the earlier group)."""
    sizes = [int(v) for v in mix.group_sizes]
    n = sum(sizes)
    exact = [n_samples * size for size in sizes]
    counts = [e // n for e in exact]
    order = sorted(range(len(sizes)), key=lambda g: (-(exact[g] % n), g))
    for g in order[: n_samples - sum(counts)]:
        counts[g] += 1
    for g, m in enumerate(counts):
        if m < 2:
            enough = math.ceil(2 * n / min(sizes))
            raise InputError(
                f"n_samples={n_samples} gives group {mix.groups[g]!r} {m} samples; each group "
                f"needs at least 2 (n_samples >= {enough} suffices)"
            )
    return np.asarray(counts, dtype=np.int64)


def _stderr(m2: float, n: int) -> float:
    return math.sqrt(m2 / n) / math.sqrt(n - 1)


def _samples_per_group(n_samples: int, model: TextureModel | MixtureModel) -> np.ndarray:
    """M_g for a mixture (:func:`_allocate`); (M,) for a single Gaussian."""
    if isinstance(model, MixtureModel):
        return _allocate(n_samples, model)
    return np.asarray([n_samples], dtype=np.int64)


def _weights(model: TextureModel | MixtureModel) -> np.ndarray:
    return model.weights if isinstance(model, MixtureModel) else np.ones(1)


def _combine_groups(means, m2s, found: _search.Search, group_samples):
    """Per group (mean, M2) of the per-chunk moments (n_chunks,) over its chunks."""
    groups = found.spans[:, 2]
    return [
        _search.sampling.combine_moments(means[groups == g], m2s[groups == g], int(m), found.chunk)
        for g, m in enumerate(group_samples)
    ]


def _stratified(stats, weights, group_samples) -> tuple[float, float, list[float]]:
    """(value, stderr, per-group stderrs) from per-group (mean, M2); one group: as today."""
    stderrs = [_stderr(m2, int(m)) for (_, m2), m in zip(stats, group_samples, strict=True)]
    if len(stats) == 1:
        return stats[0][0], stderrs[0], stderrs
    value = float(sum(w * mean for w, (mean, _) in zip(weights, stats, strict=True)))
    stderr = math.sqrt(sum((w * e) ** 2 for w, e in zip(weights, stderrs, strict=True)))
    return value, stderr, stderrs


def _specificity_result(
    model, stats: _search.ChunkStats, found: _search.Search, group_samples, common: dict
) -> SpecificityResult:
    """The SpecificityResult of one model from its per-chunk statistics in `found`."""
    per_group = _combine_groups(stats.means, stats.m2s, found, group_samples)
    value, stderr, stderrs = _stratified(per_group, _weights(model), group_samples)
    mixture = None
    if isinstance(model, MixtureModel):
        mixture = _summary(model, group_samples, per_group, stderrs, stats.counts, found.spans)
    return SpecificityResult(
        value=value,
        stderr=stderr,
        n_images=_joint(model).n_images,
        n_modes=_joint(model).n_modes,
        nearest_counts=stats.counts.sum(axis=0),
        mixture=mixture,
        **common,
    )


def _summary(mix, group_samples, stats, stderrs, counts, spans) -> MixtureSummary:
    """The MixtureSummary from per-chunk nearest counts (n_chunks, n_images)."""
    per_group = np.stack([counts[spans[:, 2] == g].sum(axis=0) for g in range(mix.n_groups)])
    onehot = np.zeros((mix.n_images, mix.n_groups), dtype=np.int64)
    onehot[np.arange(mix.n_images), mix.image_groups] = 1
    return MixtureSummary(
        groups=mix.groups,
        sizes=mix.group_sizes,
        n_modes=np.asarray([b.shape[0] for b in mix.bases], dtype=np.int64),
        weights=mix.weights,
        n_samples=np.asarray(group_samples, dtype=np.int64),
        values=np.asarray([mean for mean, _ in stats]),
        stderrs=np.asarray(stderrs),
        nearest_counts=per_group @ onehot,
    )


def _check_modes(model: TextureModel) -> None:
    if model.n_modes >= _search.sampling.MAX_MODES:
        raise InputError(f"the model has {model.n_modes} modes; at most 262143 are supported")


def _generalization_values(gen_min: np.ndarray, distance: str, exponent: float) -> np.ndarray:
    raw = gen_min.min(axis=0)
    if distance == "l2":
        raw = np.sqrt(raw)
    return raw**exponent


def texture_measures(
    images,
    *,
    n_samples: int = 100_000,
    distance: str = "l1",
    exponent: float = 1.0,
    seed: int = 0,
    mask=None,
    backend: str = "auto",
    groups=None,
    progress: bool = False,
    desc: str = "specificity",
) -> tuple[SpecificityResult, GeneralizationResult]:
    """Specificity and generalization from one pass over the same M samples.

    Takes the same arguments as :func:`specificity`; use it when both are wanted.
    `progress` shows a progress bar (labelled `desc`) on stderr during the search; the
    numbers do not depend on it.

    Returns
    -------
    SpecificityResult, GeneralizationResult

    Examples
    --------
    A mixture from the N x N Gram matrix of the centred images alone (as
    :mod:`itk_nrreval._pipeline` builds its models), two groups of 4:

    >>> import numpy as np, itk_nrreval as nr
    >>> flat = np.random.default_rng(0).normal(size=(8, 50))
    >>> centred = flat - flat.mean(axis=0)
    >>> model = nr.TextureModel.from_gram(centred @ centred.T)
    >>> spec, gen = texture_measures(model, groups=["t1"] * 4 + ["t2"] * 4, n_samples=1000)
    >>> int(spec.mixture.nearest_counts.sum())
    1000

    Notes
    -----
    For N below a measured crossover (``_BLOCKED_MIN_IMAGES``: 800 images for L1, 150 for
    L2) each sample is compared with all N training points in turn. Above it, blocks of
    samples are compared with cache-sized tiles of the training set (L1), or through one
    matrix product per block with every near-minimum candidate re-summed exactly (L2); both
    give bit-identical results to the per-sample search. Time is ``c M N (N - 1)`` for
    N - 1 modes; memory O(N^2) for the training parameters plus O(S (N + n_modes)) per
    block of S samples.

    A mixture (``groups``) runs the same searches; drawing a sample of group g in the joint
    space adds ``n_modes x K_g`` multiply-adds (K_g = N_g - 1) to the search's ``N x n_modes``
    (measured on 2 shared cores, two equal groups: 0.6-1.4x the single-Gaussian time at
    N = 36-40, 1.0-1.6x at N = 300, 1.3-2x at N = 1000). One group runs exactly the
    single-Gaussian kernels.
    """
    seed = _check_options(n_samples, distance, exponent, seed)
    _search.check_backend(backend)
    model = _fit(images, mask, groups)
    joint = _joint(model)
    _check_modes(joint)
    group_samples = _samples_per_group(int(n_samples), model)
    found = _search.search(
        [model],
        samples_per_group=group_samples,
        seed=seed,
        distance=distance,
        exponent=float(exponent),
        backend=backend,
        progress=progress,
        desc=desc,
    )
    common = dict(n_samples=int(n_samples), distance=distance, exponent=float(exponent), seed=seed)
    (stats,) = found.models
    spec = _specificity_result(model, stats, found, group_samples, common)
    values = _generalization_values(stats.gen, distance, exponent)
    gen_result = GeneralizationResult(
        value=float(values.mean()),
        stderr=float(values.std() / math.sqrt(joint.n_images - 1)),
        n_samples=int(n_samples),
        n_images=joint.n_images,
        distance=distance,
        exponent=float(exponent),
        seed=seed,
        nearest_distances=values,
        groups=None if spec.mixture is None else spec.mixture.groups,
    )
    return spec, gen_result


def specificity(
    images,
    *,
    n_samples: int = 100_000,
    distance: str = "l1",
    exponent: float = 1.0,
    seed: int = 0,
    mask=None,
    backend: str = "auto",
    groups=None,
) -> SpecificityResult:
    """Specificity of the shape-free texture model of a set of registered images.

    Parameters
    ----------
    images : ndarray of shape (n_images, *spatial), sequence of sitk.Image or paths, \
TextureModel or MixtureModel
        N >= 3 registered images on one grid, or a model already fitted to them.
    n_samples : int
        M, the number of model samples. The standard error falls as 1 / sqrt(M).
    distance : {"l1", "l2"}
        Distance in the space of non-normalized texture parameters. ``"l2"`` equals the
        Euclidean distance between images; ``"l1"`` (the paper's choice) sums absolute
        differences along the modes.
    exponent : float
        The paper's lambda: each nearest distance is raised to this power.
    seed : int
        Seed of the standard normals. The same seed gives the same numbers, and models with
        the same seed share their standard normals mode by mode (common random numbers).
    mask : ndarray of bool of shape (*spatial), sitk.Image, path, or None
        Evaluate only voxels inside the mask.
    backend : {"auto", "cpu", "torch"}
        Where distances are computed. ``"torch"`` uses PyTorch (``pip install
        'itk-nrreval[gpu]'``) on CUDA when available, else on the CPU, in float64: the same
        normals, equal results to rounding. ``"auto"`` uses torch only for large N when a CUDA
        device is present, else the CPU; ``"cpu"`` never uses torch.
    groups : sequence of hashable, length n_images, or None
        Each image's group (e.g. its modality, ``"t1"`` / ``"t2"``). None: one Gaussian,
        the paper's model. Given: a Gaussian mixture with one Gaussian per group
        (:class:`~itk_nrreval.measures.model.MixtureModel`: the group's mean and every non-zero mode
        of its PCA, N_g - 1 for generic data, unbiased variances), weighted ``N_g / N``; every
        group needs at least 2 images. One group gives the same numbers as None.

    Returns
    -------
    SpecificityResult
        With ``groups``, ``mixture`` holds the per-group values and the group-to-group
        nearest counts.

    Raises
    ------
    ValueError
        An unknown `distance` or `backend`, a bad `n_samples` or `exponent`, or
        ``backend="torch"`` without PyTorch installed.
    InputError
        Bad `groups`: not one hashable label per image, a group of 1 image, or a group whose
        images are all identical; an `n_samples` that leaves a group fewer than 2 samples;
        or a `seed` that is not an integer in ``[0, 2**63)``.

    Notes
    -----
    Samples are ``b ~ N(0, diag(mode_variances))``, drawn in chunks that are never stored,
    so memory does not grow with M. Twining et al., IEEE TMI, Section III-A, eqs. (4)-(5).

    For a mixture the samples are stratified: M is split in proportion to the weights
    (``M_g``, largest remainders first), group g drawing samples number
    ``offset_g .. offset_g + M_g - 1`` (``offset_g = sum_{h<g} M_h``, groups in order of
    first appearance); sample mu of group g is ``mean_g + sum_k z(seed, mu, k) sd_gk u_gk``.
    Each sample's distance is to the nearest of all N training images, in the joint
    parameter space of the N images (so L2 is the image-space distance, and L1 sums along
    the joint modes, as for one Gaussian). ``S = sum_g (N_g / N) S_g`` is unbiased for the
    mixture's specificity and, unlike drawing each sample's group at random, carries no
    variance from the group draw: ``stderr^2 = sum_g (N_g / N)^2 stderr_g^2``. The group of
    sample mu and its normals depend only on the seed, M and the group sizes, so two
    registrations of one image set share them (common random numbers, group by group).

    Examples
    --------
    >>> import numpy as np, itk_nrreval as nr
    >>> images = np.random.default_rng(0).normal(size=(10, 32, 32))
    >>> r = nr.specificity(images, n_samples=1000, seed=1)
    >>> int(r.nearest_counts.sum())
    1000
    """
    return texture_measures(
        images,
        n_samples=n_samples,
        distance=distance,
        exponent=exponent,
        seed=seed,
        mask=mask,
        backend=backend,
        groups=groups,
    )[0]


def generalization(
    images,
    *,
    n_samples: int = 100_000,
    distance: str = "l1",
    exponent: float = 1.0,
    seed: int = 0,
    mask=None,
    backend: str = "auto",
    groups=None,
) -> GeneralizationResult:
    """Generalization in the paper's converse sense: training images' distance to the samples.

    For each training image, the distance to its nearest of M model samples, to the power
    `exponent`, averaged over the N images (stderr ``STD / sqrt(N - 1)``). Arguments as
    :func:`specificity`. Its error cannot be reduced by drawing more samples, which is why the
    paper prefers specificity. For the shape-modelling convention (leave-one-out
    reconstruction error) see :func:`loo_generalization`. With `groups`, the samples are
    the mixture's (all groups' samples, as in :func:`specificity`).

    Returns
    -------
    GeneralizationResult
        ``nearest_distances`` has shape (n_images,), in training-image order.
    """
    return texture_measures(
        images,
        n_samples=n_samples,
        distance=distance,
        exponent=exponent,
        seed=seed,
        mask=mask,
        backend=backend,
        groups=groups,
    )[1]


def compare_specificity(
    a_images,
    b_images,
    *,
    n_samples: int = 100_000,
    distance: str = "l1",
    exponent: float = 1.0,
    seed: int = 0,
    mask=None,
    groups=None,
) -> SpecificityComparison:
    """Specificity of two registrations of one image set, and their paired difference.

    Both models see the same standard normals (common random numbers), so the paired
    difference ``a - b`` has a much smaller standard error than either value alone when the
    models are similar. Arguments as :func:`specificity`; both sets must have the same N.
    From N = ``_BLOCKED_MIN_IMAGES`` on, the blocked search serves both models (CPU only).
    With `groups` (the same for both registrations), both are mixtures and share, group by
    group, the samples' numbers and normals; ``difference = sum_g (N_g / N) d_g`` over the
    per-group mean paired differences, with the stratified standard error.

    Returns
    -------
    SpecificityComparison
    """
    seed = _check_options(n_samples, distance, exponent, seed)
    ma, mb = _fit(a_images, mask, groups), _fit(b_images, mask, groups)
    _check_modes(_joint(ma))
    _check_modes(_joint(mb))
    if _joint(ma).n_images != _joint(mb).n_images:
        raise InputError(
            f"compare_specificity needs two registrations of one image set: "
            f"got {_joint(ma).n_images} and {_joint(mb).n_images} images"
        )
    if isinstance(ma, MixtureModel) or isinstance(mb, MixtureModel):
        _check_same_groups(ma, mb)
    group_samples = _samples_per_group(int(n_samples), ma)
    found = _search.search(
        [ma, mb],
        samples_per_group=group_samples,
        seed=seed,
        distance=distance,
        exponent=float(exponent),
        backend="cpu",
    )
    common = dict(n_samples=int(n_samples), distance=distance, exponent=float(exponent), seed=seed)
    ra, rb = (
        _specificity_result(model, stats, found, group_samples, common)
        for model, stats in zip((ma, mb), found.models, strict=True)
    )
    paired = _combine_groups(found.difference[:, 0], found.difference[:, 1], found, group_samples)
    difference, difference_stderr, _ = _stratified(paired, _weights(ma), group_samples)
    return SpecificityComparison(ra, rb, difference=difference, difference_stderr=difference_stderr)


def _check_same_groups(ma, mb) -> None:
    """Two mixtures with the same groups, image by image, or a clear error."""
    if not (isinstance(ma, MixtureModel) and isinstance(mb, MixtureModel)):
        raise ValueError(
            "compare_specificity: both registrations must be mixtures (or neither); "
            "pass groups= for both"
        )
    if ma.groups != mb.groups or not np.array_equal(ma.image_groups, mb.image_groups):
        raise InputError("compare_specificity: the two mixtures have different groups")


def loo_generalization(images, *, n_modes: int | None = None, mask=None) -> GeneralizationResult:
    """Leave-one-out generalization: the shape-modelling convention.

    For each training image i, a model is built from the other N - 1 images keeping its first
    `n_modes` modes (all N - 2 when None), and image i is reconstructed from it; the result
    is the mean Euclidean reconstruction error (image intensity units) with
    ``stderr = STD / sqrt(N - 1)``. Lower is better.

    Computed exactly in the space of non-normalized parameters of the full model, which
    preserves Euclidean distances and contains every leave-one-out model.
    """
    model = _model(images, mask)
    if isinstance(model, MixtureModel):
        raise ValueError("loo_generalization takes images or a TextureModel, not a MixtureModel")
    b = model.training_params
    n = b.shape[0]
    if n < 4:
        raise InputError(f"leave-one-out generalization needs at least 4 images, got {n}")
    errors = np.empty(n)
    for i in range(n):
        rest = np.delete(b, i, axis=0)
        centre = rest.mean(axis=0)
        _, sv, vt = np.linalg.svd(rest - centre, full_matrices=False)
        rank = int(np.sum(sv > sv[0] * n * 1e-12))
        keep = rank if n_modes is None else min(int(n_modes), rank)
        modes = vt[:keep]
        r = b[i] - centre
        errors[i] = np.linalg.norm(r - modes.T @ (modes @ r))
    return GeneralizationResult(
        value=float(errors.mean()),
        stderr=float(errors.std() / math.sqrt(n - 1)),
        n_samples=0,
        n_images=n,
        distance="l2",
        exponent=1.0,
        seed=0,
        nearest_distances=errors,
    )
