"""Per-subject quality control at large N (issue 27, scale): the checks of flagged subjects
through changed transforms (transform_mixups) cost one eigendecomposition of the Gram
matrix, not two per alternative, and give the distances of brute-force affine fits of the
explicit vectors -- also when some images are affine combinations of others (a duplicate).
"""

from __future__ import annotations

import numpy as np
import pytest

from itk_nrreval.measures.subject_qc import (
    SubjectQC,
    leave_one_out_distances,
    transform_mixups,
)


def _distance_to_affine_span(point: np.ndarray, points: np.ndarray) -> float:
    """The Euclidean distance of `point` (v,) to the affine span of the rows of `points`,
    by least squares on the explicit vectors (the reference)."""
    origin = points[0]
    directions = (points[1:] - origin).T
    coefficients, *_ = np.linalg.lstsq(directions, point - origin, rcond=None)
    return float(np.linalg.norm(point - origin - directions @ coefficients))


def _alternative_vector(images, alt, mean) -> np.ndarray:
    """A made-up image for an alternative: another subject's image for a swap, minus
    the subject's image for an inversion, plus a little of something else (centred)."""
    rng = np.random.default_rng(1000 * alt.image + 10 * alt.transform + alt.inverse)
    base = -images[alt.transform] if alt.inverse else images[alt.image]
    return base + 0.3 * rng.normal(size=images.shape[1]) - mean


def _run(images: np.ndarray, scored: list[int], flagged: list[int]):
    """transform_mixups on `images` (n_all, v), `flagged` (largest z first) and the made-up
    alternatives; also the Gram matrix of the centred scored images and their mean."""
    n_all = images.shape[0]
    mean = images[scored].mean(axis=0)
    centred = images[scored] - mean
    gram = centred @ centred.T
    subjects = [
        SubjectQC(
            index=i,
            image=f"s{i}",
            score=1.0,
            z=float(len(flagged) - flagged.index(i)) if i in flagged else 0.0,
            flags=("far from the model",) if i in flagged else (),
        )
        for i in range(n_all)
    ]

    def products(alternatives):
        changed = np.array([_alternative_vector(images, a, mean) for a in alternatives])
        return changed @ centred.T, np.einsum("ij,ij->i", changed, changed)

    mixups = transform_mixups(
        subjects,
        images=[f"s{i}" for i in range(n_all)],
        scored=scored,
        gram=gram,
        products=products,
    )
    return mixups, gram, mean


def _brute_force(images, scored, flagged, mean):
    """Per checked subject: the best ratio own / changed distance, each to the affine span
    of the scored images but the subject and the image resampled through its transform."""
    from itk_nrreval.measures.subject_qc import Alternative

    best: dict[int, float] = {}
    for i in flagged:
        for j in flagged:
            alt = Alternative(j, i, inverse=j == i)
            others = images[[k for k in scored if k not in (i, j)]]
            own = _distance_to_affine_span(images[i], others)
            changed = _distance_to_affine_span(
                _alternative_vector(images, alt, mean) + mean, others
            )
            best[i] = max(best.get(i, 0.0), own / changed)
    return best


@pytest.mark.parametrize("duplicate", [None, "unflagged", "flagged"])
def test_mixup_ratios_are_brute_force_affine_fits_of_the_vectors(duplicate):
    """Random images (30 in 200 dimensions, two off the scores): each checked subject's best
    ratio equals least-squares fits of the explicit vectors; with a duplicated image among
    the others (the images are affinely dependent), and with a flagged one duplicated."""
    images = np.random.default_rng(7).normal(size=(32, 200))
    flagged = [20, 4, 11, 27]
    if duplicate == "unflagged":
        images[9] = images[3]
    elif duplicate == "flagged":
        images[15] = images[11]
    scored = [k for k in range(32) if k not in (6, 30)]
    mixups, _, mean = _run(images, scored, flagged)
    reference = _brute_force(images, scored, flagged, mean)
    assert sorted(mixups) == sorted(reference)
    for i, (ratio, words) in mixups.items():
        assert ratio == pytest.approx(reference[i], rel=1e-7, abs=1e-9), (i, words)


def _count_decompositions(monkeypatch) -> list[int]:
    """Record the size (the smaller of the last two dimensions) of every eigh and SVD numpy
    is asked for, passing each through to numpy: a cost counted, not timed."""
    sizes: list[int] = []
    for name in ("eigh", "svd"):
        real = getattr(np.linalg, name)

        def counting(a, *args, _real=real, **kwargs):
            sizes.append(min(np.shape(a)[-2:]))
            return _real(a, *args, **kwargs)

        monkeypatch.setattr(np.linalg, name, counting)
    return sizes


def test_mixups_cost_about_one_eigendecomposition_of_the_gram_matrix(monkeypatch):
    """N = 400 with 8 flagged subjects (64 alternatives): the checks take a few
    decompositions of an N-sized matrix, where refitting the model of the others for each
    alternative took over 100 of them. Counted, not timed."""
    images = np.random.default_rng(3).normal(size=(400, 600))
    scored = list(range(400))
    sizes = _count_decompositions(monkeypatch)
    mixups, _, _ = _run(images, scored, [5, 50, 100, 150, 200, 250, 300, 350])
    assert len(mixups) == 8
    large = [n for n in sizes if n >= 100]  # N-sized decompositions, N = 400
    assert 1 <= len(large) <= 5, sizes


def test_leave_one_out_distances_with_a_duplicate_are_brute_force_affine_fits():
    """Subject 9 is a copy of subject 3 (the images are affinely dependent): both are at
    distance 0 from the others' span, every other subject at its least-squares distance."""
    images = np.random.default_rng(11).normal(size=(24, 60))
    images[9] = images[3]
    centred = images - images.mean(axis=0)
    distances = leave_one_out_distances(centred @ centred.T)
    reference = [
        _distance_to_affine_span(images[k], np.delete(images, k, axis=0)) for k in range(24)
    ]
    np.testing.assert_allclose(distances, reference, rtol=1e-7, atol=1e-9)


def test_leave_one_out_distances_with_a_duplicate_cost_about_one_eigendecomposition(monkeypatch):
    """N = 200 with one duplicated image: the distances take a few decompositions of an
    N-sized matrix, where refitting each subject's model (an SVD of N - 1 images each,
    O(N^4)) takes N of them. Counted, not timed."""
    images = np.random.default_rng(5).normal(size=(200, 300))
    images[150] = images[40]
    centred = images - images.mean(axis=0)
    sizes = _count_decompositions(monkeypatch)
    distances = leave_one_out_distances(centred @ centred.T)
    assert max(distances[[40, 150]]) < 1e-6 < min(np.delete(distances, [40, 150]))
    large = [n for n in sizes if n >= 100]  # N-sized decompositions, N = 200
    assert 1 <= len(large) <= 3, sizes
