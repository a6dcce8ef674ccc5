"""The nearest-training search behind specificity, generalization and their paired comparison.

One entry point, :func:`search`: a batch of models (one, or a pair sharing one sample stream:
the same sample numbers, groups and standard normals, for a paired comparison) is sampled
chunk by chunk, each sample is compared with its model's N training points, and per chunk
come out the moments of the nearest distances, the nearest counts and each training point's
nearest sample (generalization); for a pair, also the moments of the paired differences.

Three searches, one protocol (:class:`_Backend`: ``run(first, last)`` over chunks, ``step``
chunks per call so a progress bar can move between calls):

* ``"per-sample"``: the fused numba kernels of :mod:`.sampling` (each sample against all N
  training points in turn; chunks in parallel);
* ``"blocked"``: :class:`.blocked.BlockedSearcher`, blocks of samples against cache-sized
  tiles (L1) or by GEMM with exact re-summation (L2); bit-identical to ``"per-sample"``;
* ``"torch"``: :class:`.blocked.TorchSearcher`, the blocks on a torch device in float64;
  equal to the CPU searches to rounding.

The public names ``"auto"`` and ``"cpu"`` are policies that pick one of them by the size of
the training set (:data:`BLOCKED_MIN_IMAGES`) and, for ``"auto"``, by the presence of CUDA.

A single Gaussian (a :class:`TextureModel`, or a :class:`MixtureModel` of one group) runs the
single-Gaussian kernels (samples ``sd * z``); a mixture of two groups or more runs the mixture
kernels (samples ``centre_g + z @ basis_g``). A single Gaussian is not run as a one-component
mixture: that would cost ``n_modes`` multiply-adds per coordinate instead of one.

The search in one place (private; :mod:`itk_nrreval.measures.specificity` is its public face):

* this module, ``itk_nrreval.measures._search``: the engine a caller uses -- :func:`search`, the
  backend names and policy (:data:`BACKENDS`, :data:`BLOCKED_MIN_IMAGES`), the results
  (:class:`Search`, :class:`ChunkStats`) and the backend protocol;
* :mod:`.sampling`: the sample stream (counter-based standard normals keyed by the seed,
  :func:`~.sampling.stream_key`, :data:`~.sampling.CHUNK`, :func:`~.sampling.mixture_spans`),
  the per-chunk moments and their combination, and the fused per-sample numba kernels;
* :mod:`.blocked`: the numba kernels and searchers for large N -- blocks of samples against
  cache-sized tiles (L1) or by GEMM with exact re-summation (L2), on the CPU or on torch.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numba
import numpy as np

from ... import _progress
from ..model import MixtureModel, TextureModel
from . import blocked, sampling

__all__ = ["BACKENDS", "PUBLIC_BACKENDS", "BLOCKED_MIN_IMAGES", "ChunkStats", "Search", "search"]

PUBLIC_BACKENDS = ("auto", "cpu", "torch")
BACKENDS = (*PUBLIC_BACKENDS, "per-sample", "blocked")
# The blocked search from this many training images on; below, the per-sample search, whose
# training matrix still fits in cache. Measured crossovers (2-core AMD EPYC, 8 MB L3,
# M = 8192, N - 1 modes; old / blocked time): L2 GEMM 0.95 at N = 120, 1.08 at 150, 1.2 at 180,
# 2.5 at 600, 5.8 at 1000; L1 0.89 at 500, 1.12 at 600, 0.94 at 700, 1.05 at 800, 1.4-1.6 at
# 1000, 1.9 at 1500 (the old path's 8 MB matrix leaves L3 near N = 1000). Tests set these to 0
# or to a huge number to force either search under "auto" and "cpu".
BLOCKED_MIN_IMAGES = {"l1": 800, "l2": 150}


@dataclass(frozen=True)
class ChunkStats:
    """One model's search, chunk by chunk.

    Attributes
    ----------
    means, m2s : ndarray of shape (n_chunks,)
        Mean and sum of squared deviations of the chunk's nearest distances, each raised to
        the power ``exponent`` (image intensity units ** exponent).
    counts : ndarray of int64, shape (n_chunks, n_images)
        How many of the chunk's samples have each training image as their nearest.
    gen : ndarray of shape (n_chunks, n_images)
        Each training image's raw distance (L1 sum, or squared L2) to the chunk's nearest
        sample.
    """

    means: np.ndarray
    m2s: np.ndarray
    counts: np.ndarray
    gen: np.ndarray


@dataclass(frozen=True)
class Search:
    """The per-chunk statistics of a batch of models on one sample stream.

    Attributes
    ----------
    spans : ndarray of int64, shape (n_chunks, 3)
        Chunk c is samples ``spans[c, 0] .. spans[c, 1] - 1`` of group ``spans[c, 2]``
        (:func:`.sampling.mixture_spans`; one group for a single Gaussian).
    chunk : int
        The longest chunk, in samples: every chunk of a group but its last has this length.
    models : tuple of ChunkStats
        One per model, in the order given.
    difference : ndarray of shape (n_chunks, 2), or None
        For a pair, per chunk (mean, M2) of the per-sample paired differences ``a - b`` of
        the nearest distances (to the power ``exponent``); None for one model.
    """

    spans: np.ndarray
    chunk: int
    models: tuple[ChunkStats, ...]
    difference: np.ndarray | None


@dataclass(frozen=True)
class _Sampled:
    """One model as the search sees it: its training points and how its samples are drawn.

    ``train`` (n_images, n_modes) are the training parameters; samples are ``sd * z`` (a
    single Gaussian: ``sd`` (n_modes,), ``centres`` and ``bases`` None) or, for group g,
    ``centres[g] + z @ bases[g]`` (a mixture: ``sd`` None).
    """

    train: np.ndarray
    sd: np.ndarray | None
    centres: np.ndarray | None
    bases: tuple[np.ndarray, ...] | None

    @property
    def components(self):
        return None if self.bases is None else list(zip(self.centres, self.bases, strict=True))


def _sampled(model: TextureModel | MixtureModel) -> _Sampled:
    if isinstance(model, MixtureModel) and model.n_groups > 1:
        return _Sampled(model.joint.training_params, None, model.centres, model.bases)
    gaussian = model.joint if isinstance(model, MixtureModel) else model
    return _Sampled(gaussian.training_params, np.sqrt(gaussian.mode_variances), None, None)


def _n_groups(model: TextureModel | MixtureModel) -> int:
    return model.n_groups if isinstance(model, MixtureModel) else 1


def check_backend(backend: str, *, choices: tuple[str, ...] = PUBLIC_BACKENDS) -> None:
    """Refuse a backend name not in `choices`, or ``"torch"`` without PyTorch installed."""
    if backend not in choices:
        raise ValueError(f"backend must be one of {choices}, got {backend!r}")
    if backend == "torch" and importlib.util.find_spec("torch") is None:
        raise ValueError(
            "backend='torch' needs PyTorch, which is not installed: "
            "pip install 'itk-nrreval[gpu]', or use backend='cpu'"
        )


def _torch_device(backend: str, n_images: int, distance: str):
    """The torch device to use, or None for the CPU searches."""
    if backend in ("cpu", "per-sample", "blocked"):
        return None
    if backend == "auto":
        # Only at large N, and only when torch is there already: never import torch (a
        # second or more) just to find out that there is no GPU.
        if n_images < BLOCKED_MIN_IMAGES[distance] or importlib.util.find_spec("torch") is None:
            return None
    import torch

    if torch.cuda.is_available():
        return torch.device("cuda")
    return torch.device("cpu") if backend == "torch" else None


def _resolve(backend: str, n_images: int, distance: str) -> tuple[str, object]:
    """The search a backend name stands for (per-sample, blocked, torch) and its torch device."""
    device = _torch_device(backend, n_images, distance)
    if device is not None:
        return "torch", device
    if backend in ("per-sample", "blocked"):
        return backend, None
    return ("blocked" if n_images >= BLOCKED_MIN_IMAGES[distance] else "per-sample"), None


def search(
    models: Sequence[TextureModel | MixtureModel],
    *,
    samples_per_group: Sequence[int],
    seed: int,
    distance: str,
    exponent: float,
    backend: str,
    chunk: int = sampling.CHUNK,
    progress: bool = False,
    desc: str = "specificity",
) -> Search:
    """Nearest training points of a batch of models' samples, per chunk: the one selector.

    Parameters
    ----------
    models : sequence of TextureModel or MixtureModel, length 1 or 2
        One model, or a pair on one sample stream (a paired comparison). A pair must have
        the same number of training images and the same number of groups.
    samples_per_group : sequence of int, shape (n_groups,)
        M_g, the samples of each group's Gaussian (one entry, M, for a single Gaussian);
        group g draws sample numbers ``offset_g .. offset_g + M_g - 1``.
    seed : int
        Seed of the standard normals (:func:`.sampling.stream_key`).
    distance : {"l1", "l2"}
        Distance in the joint parameter space.
    exponent : float
        Each nearest distance is raised to this power before its moments are taken.
    backend : str
        One of :data:`BACKENDS`: a search (``"per-sample"``, ``"blocked"``, ``"torch"``) or
        a policy choosing one (``"auto"``, ``"cpu"``; see the module's docstring).
    chunk : int
        Samples per chunk (the results agree to rounding whatever the chunk).
    progress : bool
        Show a progress bar labelled `desc` on stderr; the numbers do not depend on it.

    Returns
    -------
    Search

    Raises
    ------
    ValueError
        An unknown `backend` (or ``"torch"`` without PyTorch), a batch of neither one nor two
        models, or models or `samples_per_group` that do not agree in groups or images.
    """
    check_backend(backend, choices=BACKENDS)
    if len(models) not in (1, 2):
        raise ValueError(f"search takes one model or a pair, got {len(models)}")
    n_images = {m.n_images for m in models}
    n_groups = {_n_groups(m) for m in models}
    if len(n_images) != 1 or n_groups != {len(samples_per_group)}:
        raise ValueError(
            f"search: models of {sorted(n_images)} images and {sorted(n_groups)} groups "
            f"with samples for {len(samples_per_group)} groups"
        )
    spans = sampling.mixture_spans(samples_per_group, int(chunk))
    name, device = _resolve(backend, n_images.pop(), distance)
    job = _Job(
        models=[_sampled(m) for m in models],
        spans=spans,
        chunk=int(chunk),
        key=sampling.stream_key(seed),
        l2=distance == "l2",
        exponent=float(exponent),
    )
    runner: _Backend = _PerSample(job) if name == "per-sample" else _Searching(job, device)
    n_chunks = spans.shape[0]
    starts = range(0, n_chunks, runner.step)
    parts = [
        runner.run(first, min(first + runner.step, n_chunks))
        for first in _progress.progress_bar(starts, desc=desc, total=len(starts), enabled=progress)
    ]
    per_model = [
        ChunkStats(*(np.concatenate(arrays) for arrays in zip(*model_parts, strict=True)))
        for model_parts in zip(*(stats for stats, _ in parts), strict=True)
    ]
    difference = None if len(models) == 1 else np.concatenate([d for _, d in parts])
    return Search(spans=spans, chunk=int(chunk), models=tuple(per_model), difference=difference)


@dataclass(frozen=True)
class _Job:
    """What every backend is given: the batch, its chunks and the stream."""

    models: list[_Sampled]
    spans: np.ndarray
    chunk: int
    key: np.uint64
    l2: bool
    exponent: float


class _Backend(Protocol):
    """The protocol of a search: ``run(first, last)`` gives chunks ``first .. last - 1``.

    ``run`` returns per model its (means, m2s, counts, gen) of those chunks and, for a pair,
    the (last - first, 2) moments of the paired differences (else None). The selector calls
    it over consecutive ranges of ``step`` chunks; a chunk's numbers do not depend on the
    ranges.
    """

    step: int

    def run(self, first: int, last: int) -> tuple[list[tuple], np.ndarray | None]: ...


class _PerSample:
    """The fused numba kernels of :mod:`.sampling`, parallel over chunks."""

    def __init__(self, job: _Job):
        self.job = job
        self.train_t = [np.ascontiguousarray(m.train.T) for m in job.models]
        self.stacked = [None if m.bases is None else _stacked_bases(m.bases) for m in job.models]
        n_chunks = job.spans.shape[0]
        single_pair = len(job.models) == 2 and job.models[0].bases is None
        # A few chunks per thread per call, so a progress bar moves; the paired single-Gaussian
        # kernel runs every chunk in one call.
        self.step = n_chunks if single_pair else 4 * numba.get_num_threads()

    def run(self, first: int, last: int):
        job = self.job
        n_samples = int(job.spans[-1, 1])
        common = (job.key, job.l2, job.exponent)
        if len(job.models) == 1:
            (model,), (train_t,), (stacked,) = job.models, self.train_t, self.stacked
            if stacked is None:
                stats = sampling.run_single(
                    train_t,
                    model.sd,
                    job.key,
                    n_samples,
                    job.l2,
                    job.exponent,
                    job.chunk,
                    first,
                    last,
                )
            else:
                stats = sampling.run_mixture(
                    train_t, model.centres, *stacked, job.spans, *common, first, last
                )
            return [stats], None
        (a, b), (ta, tb), (sa, sb) = job.models, self.train_t, self.stacked
        if sa is None:
            assert (first, last) == (0, job.spans.shape[0])  # step: every chunk at once
            outputs = sampling.run_paired(
                ta, a.sd, tb, b.sd, job.key, n_samples, job.l2, job.exponent, job.chunk
            )
        else:
            spans = np.ascontiguousarray(job.spans[first:last])
            outputs = sampling.run_mixture_paired(
                ta, a.centres, *sa, tb, b.centres, *sb, spans, *common
            )
        moments, counts_a, counts_b, gen_a, gen_b = outputs
        return [
            (moments[0, :, 0], moments[0, :, 1], counts_a, gen_a),
            (moments[1, :, 0], moments[1, :, 1], counts_b, gen_b),
        ], moments[2]


class _Searching:
    """The blocked CPU or torch searchers of :mod:`.blocked`, one chunk per call."""

    step = 1

    def __init__(self, job: _Job, device):
        self.job = job
        if device is None:
            self.searchers = [blocked.BlockedSearcher(m.train, m.sd, job.l2) for m in job.models]
        else:
            self.searchers = [
                blocked.TorchSearcher(m.train, m.sd, job.l2, device) for m in job.models
            ]
        self.components = [m.components for m in job.models]

    def run(self, first: int, last: int):
        job = self.job
        return blocked.search_chunks(
            self.searchers, self.components, job.spans, job.key, job.l2, job.exponent, first, last
        )


def _stacked_bases(bases) -> tuple[np.ndarray, np.ndarray]:
    """All groups' bases stacked (sum_g K_g, n_modes) and each group's first row (G + 1,)."""
    rows = np.ascontiguousarray(np.concatenate(bases, axis=0))
    starts = np.concatenate([[0], np.cumsum([b.shape[0] for b in bases])]).astype(np.int64)
    return rows, starts
