"""Specificity and generalization of a shape-free texture model (paper, Section III).

Specificity (paper eq. 4-5): draw M samples y from the model, and average the distance from
each to its nearest training image, raised to the power lambda::

    S = 1/M sum_mu min_i |x_i - y_mu|^lambda,      stderr = STD_mu / sqrt(M - 1)

Lower is better: a model built from a good registration generates images close to the
training set. Generalization swaps the roles of the training set and the sample set
(1/N sum_i min_mu |x_i - y_mu|^lambda, stderr STD_i / sqrt(N - 1)).

All distances are computed in the space of non-normalized texture parameters, where L2
distances equal image-space L2 distances exactly (every non-zero mode is kept).
"""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass, field

import numba
import numpy as np

from . import _blocked, _sampling
from ._errors import InputError
from ._progress import progress
from .model import TextureModel

__all__ = [
    "SpecificityResult",
    "GeneralizationResult",
    "SpecificityComparison",
    "specificity",
    "generalization",
    "texture_measures",
    "compare_specificity",
    "loo_generalization",
]

_DISTANCES = ("l1", "l2")
_BACKENDS = ("auto", "cpu", "torch")
# The blocked search (itk_nrreval._blocked) from this many training images on; below, the
# per-sample search, whose training matrix still fits in cache. Measured crossovers (2-core
# AMD EPYC, 8 MB L3, M = 8192, N - 1 modes; old / blocked time): L2 GEMM 0.95 at N = 120,
# 1.08 at 150, 1.2 at 180, 2.5 at 600, 5.8 at 1000; L1 0.89 at 500, 1.12 at 600, 0.94 at 700,
# 1.05 at 800, 1.4-1.6 at 1000, 1.9 at 1500 (the old path's 8 MB matrix leaves L3 near N = 1000).
# Tests set these to 0 or to a huge number to force either path.
_BLOCKED_MIN_IMAGES = {"l1": 800, "l2": 150}


@dataclass(frozen=True)
class SpecificityResult:
    """Specificity of one texture model.

    Attributes
    ----------
    value : float
        Mean over samples of the nearest-training distance to the power ``exponent``
        (image intensity units ** exponent; L1 sums over modes). Lower is better.
    stderr : float
        ``STD / sqrt(M - 1)`` over the M per-sample values (paper, Section III-A).
    n_samples, n_images, n_modes : int
        M, N and the number of modes kept (N - 1 for generic data).
    nearest_counts : ndarray of int, shape (n_images,)
        How many samples fall in each training image's Voronoi cell (paper, Table 1).
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

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["nearest_counts"] = [int(c) for c in self.nearest_counts]
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
    """

    value: float
    stderr: float
    n_samples: int
    n_images: int
    distance: str
    exponent: float
    seed: int
    nearest_distances: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["nearest_distances"] = [float(v) for v in self.nearest_distances]
        return d


@dataclass(frozen=True)
class SpecificityComparison:
    """Specificity of two registrations of one image set on common random numbers.

    ``difference = a.value - b.value`` with ``difference_stderr`` from the per-sample paired
    differences: much smaller than combining ``a.stderr`` and ``b.stderr`` when the two
    models are alike. A negative difference means `a` is the more specific (better).
    """

    a: SpecificityResult
    b: SpecificityResult
    difference: float
    difference_stderr: float


def _check_options(n_samples: int, distance: str, exponent: float) -> None:
    if distance not in _DISTANCES:
        raise ValueError(f"distance must be one of {_DISTANCES}, got {distance!r}")
    if not (isinstance(n_samples, (int, np.integer)) and 2 <= n_samples < _sampling.MAX_SAMPLES):
        raise ValueError(f"n_samples must be an integer in [2, 2**36), got {n_samples!r}")
    if not (exponent > 0 and math.isfinite(exponent)):
        raise ValueError(f"exponent must be a positive number, got {exponent!r}")


def _model(images, mask) -> TextureModel:
    if isinstance(images, TextureModel):
        if mask is not None:
            raise ValueError("mask applies when fitting; pass it to TextureModel.from_images")
        return images
    return TextureModel.from_images(images, mask=mask)


def _check_modes(model: TextureModel) -> None:
    if model.n_modes >= _sampling.MAX_MODES:
        raise InputError(f"the model has {model.n_modes} modes; at most 262143 are supported")


def _check_backend(backend: str) -> None:
    if backend not in _BACKENDS:
        raise ValueError(f"backend must be one of {_BACKENDS}, got {backend!r}")
    if backend == "torch" and importlib.util.find_spec("torch") is None:
        raise ValueError(
            "backend='torch' needs PyTorch, which is not installed: "
            "pip install 'itk-nrreval[gpu]', or use backend='cpu'"
        )


def _torch_device(backend: str, n_images: int, distance: str):
    """The torch device to use, or None for the CPU paths."""
    if backend == "cpu":
        return None
    if backend == "auto":
        # Only at large N, and only when torch is there already: never import torch (a
        # second or more) just to find out that there is no GPU.
        if n_images < _BLOCKED_MIN_IMAGES[distance] or importlib.util.find_spec("torch") is None:
            return None
    import torch

    if torch.cuda.is_available():
        return torch.device("cuda")
    return torch.device("cpu") if backend == "torch" else None


def _single_pass(
    model: TextureModel,
    n_samples: int,
    distance: str,
    exponent: float,
    seed: int,
    backend: str,
    *,
    show: bool = False,
    desc: str = "specificity",
):
    """Per-chunk (means, m2s, counts, gen) of one model: per-sample, blocked or torch path."""
    l2 = distance == "l2"
    sd = np.sqrt(model.mode_variances)
    key = _sampling.stream_key(seed)
    chunk = _sampling.CHUNK
    n_chunks = (n_samples + chunk - 1) // chunk

    def wrap(chunks):
        return progress(chunks, desc=desc, total=n_chunks, enabled=show)

    device = _torch_device(backend, model.n_images, distance)
    if device is not None:
        return _blocked.run_single_torch(
            model.training_params, sd, key, n_samples, l2, exponent, chunk, device, wrap
        )
    if model.n_images >= _BLOCKED_MIN_IMAGES[distance]:
        return _blocked.run_single_blocked(
            model.training_params, sd, key, n_samples, l2, exponent, chunk, wrap
        )
    train_t = np.ascontiguousarray(model.training_params.T)
    # Groups of chunks, a few per thread, so that a progress bar can move between groups.
    group = 4 * numba.get_num_threads()
    parts = [
        _sampling.run_single(
            train_t, sd, key, n_samples, l2, exponent, chunk, c, min(c + group, n_chunks)
        )
        for c in progress(
            range(0, n_chunks, group),
            desc=desc,
            total=(n_chunks + group - 1) // group,
            enabled=show,
        )
    ]
    return tuple(np.concatenate(arrays) for arrays in zip(*parts, strict=True))


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

    Notes
    -----
    For N below a measured crossover (``_BLOCKED_MIN_IMAGES``: 800 images for L1, 150 for
    L2) each sample is compared with all N training points in turn. Above it, blocks of
    samples are compared with cache-sized tiles of the training set (L1), or through one
    matrix product per block with every near-minimum candidate re-summed exactly (L2); both
    give bit-identical results to the per-sample search. Time is ``c M N (N - 1)`` for
    N - 1 modes; memory O(N^2) for the training parameters plus O(S (N + n_modes)) per
    block of S samples.
    """
    _check_options(n_samples, distance, exponent)
    _check_backend(backend)
    model = _model(images, mask)
    _check_modes(model)
    chunk = _sampling.CHUNK
    means, m2s, counts, gen = _single_pass(
        model,
        int(n_samples),
        distance,
        float(exponent),
        int(seed),
        backend,
        show=progress,
        desc=desc,
    )
    mean, m2 = _sampling.combine_moments(means, m2s, int(n_samples), chunk)
    spec = SpecificityResult(
        value=mean,
        stderr=math.sqrt(m2 / n_samples) / math.sqrt(n_samples - 1),
        n_samples=int(n_samples),
        n_images=model.n_images,
        n_modes=model.n_modes,
        distance=distance,
        exponent=float(exponent),
        seed=int(seed),
        nearest_counts=counts.sum(axis=0),
    )
    values = _generalization_values(gen, distance, exponent)
    gen_result = GeneralizationResult(
        value=float(values.mean()),
        stderr=float(values.std() / math.sqrt(model.n_images - 1)),
        n_samples=int(n_samples),
        n_images=model.n_images,
        distance=distance,
        exponent=float(exponent),
        seed=int(seed),
        nearest_distances=values,
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
) -> SpecificityResult:
    """Specificity of the shape-free texture model of a set of registered images.

    Parameters
    ----------
    images : ndarray of shape (n_images, *spatial), sequence of sitk.Image or paths, or TextureModel
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

    Returns
    -------
    SpecificityResult

    Raises
    ------
    ValueError
        An unknown `distance` or `backend`, a bad `n_samples` or `exponent`, or
        ``backend="torch"`` without PyTorch installed.

    Notes
    -----
    Samples are ``b ~ N(0, diag(mode_variances))``, drawn in chunks that are never stored,
    so memory does not grow with M. Twining et al., IEEE TMI, Section III-A, eqs. (4)-(5).

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
) -> GeneralizationResult:
    """Generalization in the paper's converse sense: training images' distance to the samples.

    For each training image, the distance to its nearest of M model samples, to the power
    `exponent`, averaged over the N images (stderr ``STD / sqrt(N - 1)``). Arguments as
    :func:`specificity`. Its error cannot be reduced by drawing more samples, which is why the
    paper prefers specificity. For the shape-modelling convention (leave-one-out
    reconstruction error) see :func:`loo_generalization`.

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
) -> SpecificityComparison:
    """Specificity of two registrations of one image set, and their paired difference.

    Both models see the same standard normals (common random numbers), so the paired
    difference ``a - b`` has a much smaller standard error than either value alone when the
    models are similar. Arguments as :func:`specificity`; both sets must have the same N.
    From N = ``_BLOCKED_MIN_IMAGES`` on, the blocked search serves both models (CPU only).

    Returns
    -------
    SpecificityComparison
    """
    _check_options(n_samples, distance, exponent)
    ma, mb = _model(a_images, mask), _model(b_images, mask)
    _check_modes(ma)
    _check_modes(mb)
    if ma.n_images != mb.n_images:
        raise InputError(
            f"compare_specificity needs two registrations of one image set: "
            f"got {ma.n_images} and {mb.n_images} images"
        )
    l2 = distance == "l2"
    chunk = _sampling.CHUNK
    if ma.n_images >= _BLOCKED_MIN_IMAGES[distance]:
        run, a_params, b_params = (
            _blocked.run_paired_blocked,
            ma.training_params,
            mb.training_params,
        )
    else:
        run = _sampling.run_paired
        a_params = np.ascontiguousarray(ma.training_params.T)
        b_params = np.ascontiguousarray(mb.training_params.T)
    moments, counts_a, counts_b, gen_a, gen_b = run(
        a_params,
        np.sqrt(ma.mode_variances),
        b_params,
        np.sqrt(mb.mode_variances),
        _sampling.stream_key(seed),
        int(n_samples),
        l2,
        float(exponent),
        chunk,
    )
    stats = [
        _sampling.combine_moments(moments[j, :, 0], moments[j, :, 1], int(n_samples), chunk)
        for j in range(3)
    ]
    stderr = [math.sqrt(m2 / n_samples) / math.sqrt(n_samples - 1) for _, m2 in stats]
    common = dict(
        n_samples=int(n_samples), distance=distance, exponent=float(exponent), seed=int(seed)
    )
    ra = SpecificityResult(
        value=stats[0][0],
        stderr=stderr[0],
        n_images=ma.n_images,
        n_modes=ma.n_modes,
        nearest_counts=counts_a.sum(axis=0),
        **common,
    )
    rb = SpecificityResult(
        value=stats[1][0],
        stderr=stderr[1],
        n_images=mb.n_images,
        n_modes=mb.n_modes,
        nearest_counts=counts_b.sum(axis=0),
        **common,
    )
    return SpecificityComparison(ra, rb, difference=stats[2][0], difference_stderr=stderr[2])


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
