"""Generalized Tanimoto overlap against a brute-force all-pairs reference kept in this file."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import itk_nrreval as nr
from itk_nrreval.cli import main

WEIGHTINGS = (
    "volume",
    "inverse_volume",
    "inverse_volume_squared",
    "complexity",
    "inverse_volume_complexity",
)


# -- the reference: plain loops over pairs i < j --------------------------------------------


def _one_hot(crisp: np.ndarray, values) -> np.ndarray:
    """(N, *spatial) label maps -> (N, L, *spatial) float indicators of `values`."""
    return np.stack([(crisp == v) for v in values], axis=1).astype(np.float64)


def _brute(memberships: np.ndarray, *, spacing_np=None, mask=None) -> dict:
    """Every per-label quantity and every weighting, by all-pairs loops and numpy.gradient.

    `memberships` is (N, L, *spatial); `spacing_np` is in numpy axis order.
    """
    a = np.asarray(memberships, dtype=np.float64)
    n, n_labels = a.shape[:2]
    spatial = a.shape[2:]
    spacing_np = (1.0,) * len(spatial) if spacing_np is None else tuple(spacing_np)
    inside = np.ones(spatial, bool) if mask is None else np.asarray(mask, bool)
    p = np.zeros(n_labels)
    q = np.zeros(n_labels)
    inter = np.zeros((n, n, n_labels))  # inter[i, j] = sum_v min(a_i, a_j)
    for i in range(n):
        for j in range(i + 1, n):
            for lab in range(n_labels):
                lo = np.minimum(a[i, lab], a[j, lab])[inside].sum()
                hi = np.maximum(a[i, lab], a[j, lab])[inside].sum()
                p[lab] += lo
                q[lab] += hi
                inter[i, j, lab] = inter[j, i, lab] = lo
    vol = np.array([[a[i, lab][inside].sum() for lab in range(n_labels)] for i in range(n)])
    grad = np.zeros((n, n_labels))
    for i in range(n):
        for lab in range(n_labels):
            axes = [d for d in range(len(spatial)) if spatial[d] > 1]
            comps = np.gradient(a[i, lab], *[spacing_np[d] for d in axes], axis=axes)
            comps = [comps] if len(axes) == 1 else comps
            mag = np.sqrt(sum(c**2 for c in comps)) if axes else np.zeros(spatial)
            grad[i, lab] = mag[inside].sum()
    complexity = np.zeros(n_labels)
    target = np.zeros(n_labels)
    for lab in range(n_labels):
        carriers = [i for i in range(n) if vol[i, lab] > 0]
        complexity[lab] = np.mean([grad[i, lab] / vol[i, lab] for i in carriers])
        target[lab] = np.mean(
            [inter[i, j, lab] / vol[j, lab] for j in carriers for i in range(n) if i != j]
        )
    volume = vol.mean(axis=0) * np.prod(spacing_np)
    alphas = {
        "volume": np.ones(n_labels),
        "inverse_volume": 1 / volume,
        "inverse_volume_squared": 1 / volume**2,
        "complexity": complexity,
        "inverse_volume_complexity": complexity / volume,
    }
    return {
        "pair_min": p,
        "pair_max": q,
        "volume": volume,
        "complexity": complexity,
        "target_overlap": target,
        "jaccard": p / q,
        "dice": np.array([2 * p[k] / ((n - 1) * vol[:, k].sum()) for k in range(n_labels)]),
        "generalized": {
            w: (al @ p) / (al @ q) if (al @ q) > 0 else np.nan for w, al in alphas.items()
        },
    }


def _assert_matches(table: nr.OverlapTable, ref: dict, rtol: float = 1e-12) -> None:
    for name in ("pair_min", "pair_max", "volume", "complexity", "target_overlap"):
        np.testing.assert_allclose(getattr(table, name), ref[name], rtol=rtol, err_msg=name)
    np.testing.assert_allclose(table.jaccard, ref["jaccard"], rtol=rtol)
    np.testing.assert_allclose(table.dice, ref["dice"], rtol=rtol)
    for w in WEIGHTINGS:
        expected = ref["generalized"][w]
        if np.isnan(expected):  # every weight zero: no boundary anywhere
            with pytest.warns(RuntimeWarning, match="every label weight is zero"):
                assert np.isnan(table.generalized(w))
        else:
            assert table.generalized(w) == pytest.approx(expected, rel=rtol, abs=0), w


def _smooth_crisp(rng, n, shape, n_labels):
    """Blobby label maps: a shared random field plus per-image noise, argmax over labels."""
    base = rng.normal(size=(n_labels, *shape))
    for ax in range(1, base.ndim):
        base = base + np.roll(base, 1, axis=ax)
    fields = base + 0.7 * rng.normal(size=(n, n_labels, *shape))
    return fields.argmax(axis=1).astype(np.int16)


# -- exactness against the reference ----------------------------------------------------------


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 6),
    shape=st.lists(st.integers(1, 6), min_size=1, max_size=3),
    n_values=st.integers(2, 5),
    background=st.booleans(),
)
def test_crisp_matches_all_pairs(seed, n, shape, n_values, background):
    rng = np.random.default_rng(seed)
    crisp = rng.integers(0, n_values, size=(n, *shape)) * 3 - 2  # labels -2, 1, 4, ...
    spacing_itk = rng.uniform(0.3, 3.0, size=len(shape))
    values = np.unique(crisp)
    if not background:
        values = values[values != 0]
    table = nr.overlap_table(crisp, spacing=spacing_itk, include_background=background)
    np.testing.assert_array_equal(table.labels, values)
    ref = _brute(_one_hot(crisp, values), spacing_np=spacing_itk[::-1])
    _assert_matches(table, ref)
    np.testing.assert_array_equal(table.pair_min, np.round(table.pair_min))  # exact counts


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 7),
    shape=st.lists(st.integers(1, 6), min_size=1, max_size=3),
    n_comp=st.integers(1, 4),
    dtype=st.sampled_from([np.float64, np.float32]),
    ties=st.booleans(),
)
def test_fuzzy_matches_all_pairs(seed, n, shape, n_comp, dtype, ties):
    rng = np.random.default_rng(seed)
    a = rng.random((n, n_comp, *shape))
    if ties:  # many equal values and exact zeros and ones
        a = np.round(a * 4) / 4
    a = a.astype(dtype)
    spacing_itk = rng.uniform(0.3, 3.0, size=len(shape))
    keep = [k for k in range(n_comp) if a[:, k].any()]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an all-zero component is skipped with a warning
        if not keep:
            with pytest.raises(nr.InputError, match="no label in any"):
                nr.overlap_table(a, spacing=spacing_itk, include_background=True)
            return
        table = nr.overlap_table(a, spacing=spacing_itk, include_background=True)
    np.testing.assert_array_equal(table.labels, keep)
    assert table.fuzzy
    _assert_matches(table, _brute(a[:, keep], spacing_np=spacing_itk[::-1]))


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 13, 36, 37, 64])
def test_sorting_network_sorts(rng, n):
    from itk_nrreval.measures._overlap_kernels import _sorting_network

    lo, hi = _sorting_network(n)
    assert np.all(lo < hi) and (hi.max(initial=0) < n)
    columns = np.concatenate([rng.random((200, n)), rng.integers(0, 3, (200, n))]).T
    for a, b in zip(lo, hi, strict=True):
        columns[[a, b]] = np.sort(columns[[a, b]], axis=0)
    np.testing.assert_array_equal(columns, np.sort(columns, axis=0))


def test_many_images_and_long_runs_of_voxels(rng):
    # more images than a small network covers and more voxels than one block
    dense = np.clip(rng.random((40, 2, 5000)) * 1.4 - 0.2, 0, 1)  # sorted by the network
    sparse = np.where(rng.random((40, 2, 5000)) < 0.02, dense, 0.0)  # few values to sort
    assert (sparse[:, 1] != 0).any(axis=0).mean() < 0.5
    for a in (dense, sparse):
        _assert_matches(nr.overlap_table(a), _brute(a[:, 1:]))


@pytest.mark.parametrize("share", [0.0, 1.0])  # force the sorting network / the sparse sort
def test_both_fuzzy_kernels_on_zeros_ones_and_ties(rng, monkeypatch, share):
    from itk_nrreval.measures import _overlap_kernels

    monkeypatch.setattr(_overlap_kernels, "_NETWORK_FRACTION", share)
    a = rng.choice([0.0, 0.0, 0.0, 1.0, 1.0, 0.3, 0.7], size=(9, 3, 6, 7))
    a[:, :, :2] = rng.random((9, 3, 2, 7))
    _assert_matches(nr.overlap_table(a, include_background=True), _brute(a))


@pytest.mark.parametrize("n", [2, 5, 36, 37])
def test_packed_float32_network_on_ties_and_many_blocks(rng, monkeypatch, n):
    # float32 input sorts keys carrying the image index in their low bits; force that kernel
    # on every block, with exact zeros and ones, ties, tiny values and a partial last block
    from itk_nrreval.measures import _overlap_kernels

    monkeypatch.setattr(_overlap_kernels, "_NETWORK_FRACTION", 0.0)
    a = rng.choice([0.0, 1.0, 0.25, 0.5, 1e-30, 0.7], size=(n, 2, 3, 7, 31)).astype(np.float32)
    a[:, :, 0] = rng.random((n, 2, 7, 31))
    a[0, 1, 1] = 0.0  # one image missing from a slab of voxels
    table = nr.overlap_table(a, include_background=True)
    _assert_matches(table, _brute(a))


def test_fuzzy_default_drops_component_zero(rng):
    a = rng.random((4, 3, 5, 6))
    table = nr.overlap_table(a)
    np.testing.assert_array_equal(table.labels, [1, 2])
    _assert_matches(table, _brute(a[:, 1:]))


def test_mask_restricts_every_sum(rng):
    crisp = _smooth_crisp(rng, 5, (8, 9), 4)
    mask = np.zeros((8, 9), bool)
    mask[2:7, 1:6] = True
    table = nr.overlap_table(crisp, mask=mask, spacing=(0.5, 2.0))
    values = np.unique(crisp[:, mask])
    values = values[values != 0]
    ref = _brute(_one_hot(crisp, values), spacing_np=(2.0, 0.5), mask=mask)
    _assert_matches(table, ref)

    fuzzy = rng.random((4, 3, 8, 9))
    _assert_matches(nr.overlap_table(fuzzy, mask=mask), _brute(fuzzy[:, 1:], mask=mask))


def test_two_images_one_label_is_the_jaccard_index(rng):
    a = rng.random((12, 13)) < 0.4
    b = rng.random((12, 13)) < 0.5
    jaccard = np.sum(a & b) / np.sum(a | b)
    crisp = np.stack([a, b]).astype(np.uint8)
    for w in WEIGHTINGS:
        assert nr.generalized_overlap(crisp, weighting=w) == pytest.approx(jaccard, rel=1e-14)
    fa, fb = rng.random((2, 7, 8))
    fuzzy = np.stack([np.stack([1 - fa, fa]), np.stack([1 - fb, fb])])
    fuzzy_jaccard = np.minimum(fa, fb).sum() / np.maximum(fa, fb).sum()
    assert nr.generalized_overlap(fuzzy) == pytest.approx(fuzzy_jaccard, rel=1e-14)


def test_limit_cases():
    same = np.tile(np.array([[0, 1, 2, 2], [1, 1, 2, 0]]), (3, 1, 1))
    for w in WEIGHTINGS:
        assert nr.generalized_overlap(same, weighting=w) == 1.0
    disjoint = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert nr.generalized_overlap(disjoint, weighting="volume") == 0.0
    # a label that fills the grid in every image has no boundary: complexity weight 0
    full = np.ones((3, 4, 4), np.int32)
    table = nr.overlap_table(full)
    assert table.complexity[0] == 0.0
    with pytest.warns(RuntimeWarning, match="every label weight is zero"):
        assert np.isnan(table.generalized("complexity"))


@pytest.mark.parametrize("fuzzy", [False, True])
def test_invariant_to_image_order(rng, fuzzy):
    data = rng.random((6, 3, 7, 5, 4)) if fuzzy else _smooth_crisp(rng, 6, (7, 5, 4), 5)
    table = nr.overlap_table(data, spacing=(1.0, 0.6, 2.5))
    for perm in (rng.permutation(6), np.arange(6)[::-1]):
        other = nr.overlap_table(data[perm], spacing=(1.0, 0.6, 2.5))
        for name in ("pair_min", "pair_max", "volume", "complexity", "target_overlap"):
            np.testing.assert_allclose(getattr(other, name), getattr(table, name), rtol=1e-13)
        for w in WEIGHTINGS:
            assert other.generalized(w) == pytest.approx(table.generalized(w), rel=1e-13)


def test_one_hot_memberships_equal_crisp_maps(rng):
    crisp = _smooth_crisp(rng, 5, (6, 7, 5), 4)
    fuzzy = _one_hot(crisp, range(4))
    a, b = nr.overlap_table(crisp), nr.overlap_table(fuzzy)
    np.testing.assert_array_equal(a.labels, b.labels)
    for name in ("pair_min", "pair_max", "volume", "complexity", "target_overlap"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-13)


# -- physical spacing and the complexity weight ----------------------------------------------


def test_complexity_of_a_slab_follows_the_x_spacing_only():
    # Label 1 fills x < k of a (z, y, x) grid: |grad| = 1 / (2 hx) on the two voxel layers
    # beside the face, so sum |grad| / volume = (2 ny nz / (2 hx)) / (k ny nz) = 1 / (k hx).
    k, hx, hy, hz = 3, 0.5, 2.0, 3.0
    crisp = np.zeros((2, 4, 5, 8), np.int32)
    crisp[:, :, :, :k] = 1
    table = nr.overlap_table(crisp, spacing=(hx, hy, hz))
    assert table.complexity[0] == pytest.approx(1 / (k * hx), rel=1e-14)
    assert table.volume[0] == pytest.approx(k * 4 * 5 * hx * hy * hz, rel=1e-14)


def test_complexity_with_anisotropic_spacing_against_slicing_gradient(rng):
    # An independent gradient: central differences by hand, one-sided at the faces.
    def grad_mag(f, h):
        total = np.zeros_like(f)

        def sl(ax, a, b):
            return tuple(slice(a, b) if d == ax else slice(None) for d in range(f.ndim))

        for ax, step in enumerate(h):
            g = np.empty_like(f)
            g[sl(ax, 1, -1)] = (f[sl(ax, 2, None)] - f[sl(ax, None, -2)]) / (2 * step)
            g[sl(ax, 0, 1)] = (f[sl(ax, 1, 2)] - f[sl(ax, 0, 1)]) / step
            g[sl(ax, -1, None)] = (f[sl(ax, -1, None)] - f[sl(ax, -2, -1)]) / step
            total += g**2
        return np.sqrt(total)

    h_itk = (0.4, 1.1, 2.7)
    h_np = h_itk[::-1]
    crisp = _smooth_crisp(rng, 4, (5, 6, 7), 3)
    fuzzy = rng.random((4, 3, 5, 6, 7))
    for data, mem in ((crisp, _one_hot(crisp, [1, 2])), (fuzzy, fuzzy[:, 1:])):
        table = nr.overlap_table(data, spacing=h_itk)
        expected = [
            np.mean([grad_mag(mem[i, k], h_np).sum() / mem[i, k].sum() for i in range(4)])
            for k in range(2)
        ]
        np.testing.assert_allclose(table.complexity, expected, rtol=1e-12)


@pytest.mark.parametrize("slabs", [(3, 6), (0, 2), (8, 10), (1, 9)])
def test_complexity_of_memberships_confined_to_a_few_slabs(rng, slabs):
    a = np.zeros((5, 2, 10, 6, 7))
    a[:, 1, slabs[0] : slabs[1]] = rng.random((5, slabs[1] - slabs[0], 6, 7))
    mask = rng.random((10, 6, 7)) < 0.8
    for m in (None, mask):
        table = nr.overlap_table(a, spacing=(0.6, 1.7, 2.2), mask=m)
        _assert_matches(table, _brute(a[:, 1:], spacing_np=(2.2, 1.7, 0.6), mask=m))


def test_images_bring_their_spacing(rng, tmp_path):
    crisp = _smooth_crisp(rng, 3, (4, 5, 6), 3).astype(np.uint8)
    images = []
    for i, arr in enumerate(crisp):
        img = sitk.GetImageFromArray(arr)
        img.SetSpacing((0.5, 1.5, 3.0))
        images.append(img)
        sitk.WriteImage(img, str(tmp_path / f"l{i}.nii.gz"))
    reference = nr.overlap_table(crisp, spacing=(0.5, 1.5, 3.0))
    for given_ in (images, sorted(tmp_path.glob("l*.nii.gz"))):
        table = nr.overlap_table(given_)
        assert table.spacing == pytest.approx((0.5, 1.5, 3.0))
        np.testing.assert_allclose(table.complexity, reference.complexity, rtol=1e-6)
        np.testing.assert_array_equal(table.pair_min, reference.pair_min)
    with pytest.raises(ValueError, match="spacing is taken from the images' geometry"):
        nr.overlap_table(images, spacing=(1, 1, 1))


def test_multicomponent_images_are_memberships(rng):
    a = rng.random((3, 4, 5, 6))  # (N, L, y, x)
    images = [sitk.GetImageFromArray(np.moveaxis(m, 0, -1), isVector=True) for m in a]
    table = nr.overlap_table(images)
    assert table.fuzzy
    _assert_matches(table, _brute(a[:, 1:]))


# -- options and bad input -------------------------------------------------------------------


def test_label_values_select_and_absent_ones_warn(rng):
    crisp = _smooth_crisp(rng, 4, (6, 6), 4)
    with pytest.warns(UserWarning, match=r"labels \[7\] are absent from every image"):
        table = nr.overlap_table(crisp, label_values=[3, 7, 1])
    np.testing.assert_array_equal(table.labels, [1, 3])
    assert table.skipped_labels == (7,)
    _assert_matches(table, _brute(_one_hot(crisp, [1, 3])))
    fuzzy = rng.random((3, 4, 5))
    fuzzy[:, 2] = 0.0
    with pytest.warns(UserWarning, match=r"labels \[2\] are absent"):
        table = nr.overlap_table(fuzzy)
    np.testing.assert_array_equal(table.labels, [1, 3])
    with pytest.raises(ValueError, match=r"component indices 0\.\.3, got \[4\]"):
        nr.overlap_table(fuzzy, label_values=[4])


def test_bad_weighting_names_argument_value_and_choices():
    crisp = np.array([[0, 1], [1, 1]])
    with pytest.raises(ValueError, match=r"weighting must be one of \('volume'.*got 'dice'"):
        nr.generalized_overlap(crisp, weighting="dice")
    with pytest.raises(ValueError, match=r"weighting must be one of .*got 'Volume'"):
        nr.overlap_table(crisp).generalized("Volume")


def test_bad_inputs_raise_input_error():
    with pytest.raises(nr.InputError, match="need at least 2"):
        nr.overlap_table(np.array([[0, 1, 1]]))
    with pytest.raises(nr.InputError, match="no label other than background 0"):
        nr.overlap_table(np.zeros((3, 4, 4), np.int32))
    with pytest.raises(nr.InputError, match=r"label map\[1\]: membership values outside \[0, 1\]"):
        nr.overlap_table(np.array([[[0.0, 1.0]], [[0.5, 2.0]]]))
    with pytest.raises(nr.InputError, match="the list is empty"):
        nr.overlap_table([])
    with pytest.raises(ValueError, match=r"spacing must be 2 positive numbers"):
        nr.overlap_table(np.zeros((2, 3, 3), np.int8) + 1, spacing=(1.0, -1.0))
    scalar = sitk.GetImageFromArray(np.ones((3, 3), np.uint8))
    vector = sitk.GetImageFromArray(np.ones((3, 3, 2)), isVector=True)
    with pytest.raises(nr.InputError, match=r"label map\[1\]: has 2 components per voxel"):
        nr.overlap_table([scalar, vector])


def test_float_scalar_images_must_hold_integers():
    ok = [sitk.GetImageFromArray(np.array([[0.0, 1.0], [2.0, 1.0]])) for _ in range(2)]
    assert nr.generalized_overlap(ok, weighting="volume") == 1.0
    bad = ok + [sitk.GetImageFromArray(np.array([[0.0, 1.5], [2.0, 1.0]]))]
    with pytest.raises(nr.InputError, match=r"label map\[2\]: non-integer values in a crisp"):
        nr.overlap_table(bad)


# -- computing only what is asked for ----------------------------------------------------------


def _assert_partial_matches(table: nr.OverlapTable, ref: dict, *, complexity, target) -> None:
    """As _assert_matches, for a table built with some quantities left out (NaN)."""
    for name in ("pair_min", "pair_max", "volume"):
        np.testing.assert_allclose(getattr(table, name), ref[name], rtol=1e-12, err_msg=name)
    for name, computed in (("complexity", complexity), ("target_overlap", target)):
        if computed:
            np.testing.assert_allclose(getattr(table, name), ref[name], rtol=1e-12)
        else:
            assert np.isnan(getattr(table, name)).all(), name
    assert table.has_complexity == complexity and table.has_target_overlap == target
    for w in WEIGHTINGS:
        if w in ("complexity", "inverse_volume_complexity") and not complexity:
            continue
        expected = ref["generalized"][w]
        if np.isnan(expected):
            with pytest.warns(RuntimeWarning, match="every label weight is zero"):
                assert np.isnan(table.generalized(w))
        else:
            assert table.generalized(w) == pytest.approx(expected, rel=1e-12, abs=0), w


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 7),
    shape=st.lists(st.integers(1, 7), min_size=1, max_size=3),
    n_values=st.integers(2, 12),
    use_mask=st.booleans(),
    complexity=st.booleans(),
    target=st.booleans(),
)
def test_crisp_kernel_options_match_all_pairs(
    seed, n, shape, n_values, use_mask, complexity, target
):
    # up to 12 labels for 2 images: both the dense count sweep and the revisit of the images
    rng = np.random.default_rng(seed)
    crisp = rng.integers(0, n_values, size=(n, *shape)) * 2 - 3
    spacing_itk = rng.uniform(0.3, 3.0, size=len(shape))
    mask = rng.random(shape) < 0.6 if use_mask else None
    if mask is not None and not mask.any():
        mask = None
    inside = crisp[:, mask] if mask is not None else crisp
    values = np.unique(inside)
    values = values[values != 0]
    if values.size == 0:
        return
    table = nr.overlap_table(
        crisp, spacing=spacing_itk, mask=mask, complexity=complexity, target_overlap=target
    )
    np.testing.assert_array_equal(table.labels, values)
    ref = _brute(_one_hot(crisp, values), spacing_np=spacing_itk[::-1], mask=mask)
    _assert_partial_matches(table, ref, complexity=complexity, target=target)


@pytest.mark.parametrize(
    "kind",
    ["int8", "uint16", "bool", "wide_range", "huge_range", "strided_rows", "many_labels"],
)
def test_crisp_label_encodings_and_paths(rng, kind):
    # lookup table, range scan before counting, binary search; one voxel block and several
    shape = (5, 9, 131)  # 5895 voxels: several count blocks, the last one partial
    n = 4
    if kind == "int8":
        crisp = rng.integers(-3, 4, size=(n, *shape)).astype(np.int8)
    elif kind == "uint16":
        crisp = (rng.integers(0, 5, size=(n, *shape)) * 1000).astype(np.uint16)
    elif kind == "bool":
        crisp = rng.random((n, *shape)) < 0.4
    elif kind == "wide_range":  # more than 1024 values apart: scanned for presence first
        crisp = rng.choice(np.array([0, 3, 5000, -90000], np.int32), size=(n, *shape))
    elif kind == "huge_range":  # more than 2^22 apart: binary search instead of a table
        crisp = rng.choice(np.array([0, 7, 1 << 40, -(1 << 33)]), size=(n, *shape))
    elif kind == "strided_rows":  # one component of a larger array: rows not adjacent
        crisp = rng.integers(0, 4, size=(n, 3, *shape)).astype(np.int16)[:, 1]
    else:  # more labels than twice the images
        crisp = rng.integers(0, 40, size=(n, *shape)).astype(np.int32)
    mask = rng.random(shape) < 0.8
    values = np.unique(crisp[:, mask])
    values = values[values != 0]
    table = nr.overlap_table(crisp, mask=mask, spacing=(0.7, 1.3, 2.0))
    np.testing.assert_array_equal(table.labels, values.astype(np.int64))
    ref = _brute(_one_hot(crisp, values), spacing_np=(2.0, 1.3, 0.7), mask=mask)
    _assert_matches(table, ref)


@pytest.mark.parametrize("fuzzy", [False, True])
def test_results_do_not_depend_on_the_thread_count(rng, fuzzy):
    numba = pytest.importorskip("numba")
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs two numba threads")
    if fuzzy:
        data = rng.random((9, 3, 6, 40, 50)).astype(np.float32)
        data[:, :, :, :20] = np.round(data[:, :, :, :20])  # sparse and sorted blocks
    else:
        data = _smooth_crisp(rng, 9, (6, 40, 50), 7)
    mask = rng.random(data.shape[-3:]) < 0.9
    before = numba.get_num_threads()
    tables = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            tables.append(nr.overlap_table(data, mask=mask, spacing=(0.5, 1.0, 2.0)))
    finally:
        numba.set_num_threads(before)
    one, two = tables
    for name in ("pair_min", "pair_max", "volume", "complexity", "target_overlap"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)


def test_table_without_complexity_says_so(rng):
    crisp = _smooth_crisp(rng, 4, (6, 7), 3)
    table = nr.overlap_table(crisp, complexity=False, target_overlap=False)
    assert not table.has_complexity and not table.has_target_overlap
    assert np.isnan(table.complexity).all() and np.isnan(table.target_overlap).all()
    for w in ("complexity", "inverse_volume_complexity"):
        with pytest.raises(ValueError, match=r"table was built with complexity=False"):
            table.weights(w)
        with pytest.raises(ValueError, match=r"table was built with complexity=False"):
            table.generalized(w)
    full = nr.overlap_table(crisp)
    assert table.generalized("inverse_volume") == full.generalized("inverse_volume")
    data = table.to_dict()
    text = json.dumps(data, allow_nan=False)  # valid JSON: None, never NaN
    assert data["generalized"]["complexity"] is None
    assert data["generalized"]["inverse_volume_complexity"] is None
    assert data["generalized"]["volume"] == full.generalized("volume")
    assert all(r["complexity"] is None and r["target_overlap"] is None for r in data["labels"])
    assert json.loads(text)["labels"][0]["jaccard"] == full.rows()[0]["jaccard"]
    rows = table.rows()
    assert all(np.isnan(r["complexity"]) and np.isnan(r["target_overlap"]) for r in rows)
    fuzzy = rng.random((3, 3, 5, 6))
    ftable = nr.overlap_table(fuzzy, complexity=False)
    assert ftable.has_target_overlap and not ftable.has_complexity
    with pytest.raises(ValueError, match=r"table was built with complexity=False"):
        ftable.generalized("complexity")
    np.testing.assert_array_equal(ftable.target_overlap, nr.overlap_table(fuzzy).target_overlap)


def test_to_dict_of_undefined_overlap_is_valid_json():
    full = np.ones((3, 4, 4), np.int32)  # no boundary: complexity weights all zero
    with pytest.warns(RuntimeWarning, match="every label weight is zero"):
        data = nr.overlap_table(full).to_dict()
    assert data["generalized"]["complexity"] is None
    json.dumps(data, allow_nan=False)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 6),
    shape=st.lists(st.integers(1, 6), min_size=1, max_size=3),
    fuzzy=st.booleans(),
    use_mask=st.booleans(),
    weighting=st.sampled_from(WEIGHTINGS),
)
def test_generalized_overlap_equals_the_full_table(seed, n, shape, fuzzy, use_mask, weighting):
    # generalized_overlap computes only what its weighting needs; the number must not change
    rng = np.random.default_rng(seed)
    data = rng.random((n, 3, *shape)) if fuzzy else rng.integers(0, 4, size=(n, *shape))
    mask = rng.random(shape) < 0.7 if use_mask else None
    if mask is not None and not mask.any():
        mask = None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # absent components, undefined complexity weights
        try:
            full = nr.overlap_table(data, mask=mask).generalized(weighting)
        except nr.InputError:  # nothing to evaluate inside the mask
            return
        fast = nr.generalized_overlap(data, weighting=weighting, mask=mask)
    assert fast == full or (np.isnan(fast) and np.isnan(full))


# -- the shared kernels and OverlapTable.from_sums ------------------------------------------------


def _brute_pairs(a: np.ndarray, mask=None):
    """(pair_min, pair_max, volume, target_sums) of (N, n) memberships by all-pairs loops."""
    a = np.asarray(a, np.float64)
    inside = np.ones(a.shape[1], bool) if mask is None else mask
    n = a.shape[0]
    p = q = 0.0
    target = np.zeros(n)
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            lo = np.minimum(a[i], a[j])[inside].sum()
            target[i] += lo
            if i < j:
                p += lo
                q += np.maximum(a[i], a[j])[inside].sum()
    return p, q, a[:, inside].sum(axis=1), target


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("use_mask", [False, True])
def test_membership_pair_sums_against_all_pairs(rng, dtype, use_mask):
    from itk_nrreval.measures._overlap_kernels import membership_pair_sums

    for n in (2, 5, 37):
        a = rng.choice([0.0, 0.0, 1.0, 0.5, 0.25], size=(n, 900))
        a[:, :300] = rng.random((n, 300))  # dense blocks go to the sorting network
        a = a.astype(dtype)
        mask = rng.random(900) < 0.7 if use_mask else None
        p, q, vol, target = membership_pair_sums(a, mask=mask)
        ref = _brute_pairs(a, mask)
        assert isinstance(p, float) and isinstance(q, float)
        assert p == pytest.approx(ref[0], rel=1e-12) and q == pytest.approx(ref[1], rel=1e-12)
        np.testing.assert_allclose(vol, ref[2], rtol=1e-12)
        np.testing.assert_allclose(target, ref[3], rtol=1e-12)
        assert vol.shape == target.shape == (n,) and vol.dtype == np.float64


def test_membership_gradient_sum_against_numpy_gradient(rng):
    from itk_nrreval.measures._overlap_kernels import (
        membership_gradient_sum,
        membership_gradient_sums,
    )

    for shape, spacing_itk in (((7, 5, 6), (0.5, 1.5, 2.5)), ((1, 9), (1.2, 3.0)), ((11,), (0.7,))):
        a = rng.random((3, *shape)) * (rng.random((3, *shape)) < 0.5)
        a[0] = 0.0
        a[1, ...] = 0.0
        a[1].reshape(-1)[a[1].size // 2] = 0.75  # one voxel: a few slabs around it only
        mask = rng.random(shape) < 0.7
        axes = [d for d in range(len(shape)) if shape[d] > 1]
        spacing_np = spacing_itk[::-1]
        for m in (None, mask):
            inside = np.ones(shape, bool) if m is None else m
            expected = []
            for i in range(3):
                comps = np.gradient(a[i], *[spacing_np[d] for d in axes], axis=axes)
                comps = [comps] if len(axes) == 1 else comps
                expected.append(np.sqrt(sum(c**2 for c in comps))[inside].sum())
            flat_mask = None if m is None else m.reshape(-1)
            one = [
                membership_gradient_sum(
                    a[i].reshape(-1), shape=shape, spacing=spacing_itk, mask=flat_mask
                )
                for i in range(3)
            ]
            np.testing.assert_allclose(one, expected, rtol=1e-12, atol=1e-12)
            assert one[0] == 0.0
            many = membership_gradient_sums(
                a.reshape(3, -1), shape=shape, spacing=spacing_itk, mask=flat_mask
            )
            np.testing.assert_array_equal(many, one)
    with pytest.raises(ValueError, match="does not hold"):
        membership_gradient_sum(np.zeros(10), shape=(3, 4), spacing=(1, 1))
    with pytest.raises(ValueError, match="spacing must be 2 positive numbers"):
        membership_gradient_sum(np.zeros(12), shape=(3, 4), spacing=(1,))


def test_label_map_sums_counts_pairs_exactly(rng):
    from itk_nrreval.measures._overlap_kernels import label_map_sums

    crisp = rng.integers(0, 5, size=(6, 700))
    mask = rng.random(700) < 0.6
    for values, m, target in (([1, 3, 9], None, True), ([0, 4], mask, False), (None, mask, True)):
        got_values, pm, vol, tgt = label_map_sums(
            crisp, values=values, exclude=(0, 2), mask=m, target_overlap=target
        )
        inside = np.ones(700, bool) if m is None else m
        expected_values = [1, 3, 4] if values is None else values
        np.testing.assert_array_equal(got_values, expected_values)
        for k, v in enumerate(expected_values):
            hit = (crisp == v) & inside
            c = hit.sum(axis=0)
            assert pm[k] == (c * (c - 1) // 2).sum()
            np.testing.assert_array_equal(vol[:, k], hit.sum(axis=1))
            if target:
                np.testing.assert_array_equal(tgt[:, k], (hit * (c - 1)).sum(axis=1))
        assert pm.dtype == vol.dtype == np.int64
        assert (tgt is None) != target
    with pytest.raises(ValueError, match="integer dtype"):
        label_map_sums(np.zeros((2, 5)))


@pytest.mark.parametrize("fuzzy", [False, True])
def test_from_sums_round_trip_equals_overlap_table(rng, fuzzy):
    from itk_nrreval.measures._overlap_kernels import (
        label_map_gradient_sums,
        label_map_sums,
        membership_gradient_sums,
        membership_pair_sums,
    )

    shape, spacing_itk = (5, 6, 7), (0.6, 1.1, 2.3)
    mask = rng.random(shape) < 0.8
    flat_mask = mask.reshape(-1)
    if fuzzy:
        data = rng.random((5, 4, *shape)) * (rng.random((5, 4, *shape)) < 0.6)
        labels = np.arange(1, 4)
        flat = data.reshape(5, 4, -1)
        vol, target, grad = (np.zeros((5, 3)) for _ in range(3))
        p, q = np.zeros(3), np.zeros(3)
        for k, comp in enumerate(labels):
            p[k], q[k], vol[:, k], target[:, k] = membership_pair_sums(
                flat[:, comp], mask=flat_mask
            )
            grad[:, k] = membership_gradient_sums(
                flat[:, comp], shape=shape, spacing=spacing_itk, mask=flat_mask
            )
    else:
        data = _smooth_crisp(rng, 5, shape, 4)
        flat = data.reshape(5, -1)
        labels, pm, vol, target = label_map_sums(flat, exclude=(0,), mask=flat_mask)
        grad = label_map_gradient_sums(flat, labels, shape=shape, spacing=spacing_itk, mask=mask)
        p, q = pm, 4 * vol.sum(axis=0) - pm
    table = nr.OverlapTable.from_sums(
        labels, vol, target, grad, p, q, spacing=spacing_itk, fuzzy=fuzzy
    )
    reference = nr.overlap_table(data, mask=mask, spacing=spacing_itk)
    for name in ("labels", "pair_min", "pair_max", "volume", "complexity", "target_overlap"):
        np.testing.assert_array_equal(getattr(table, name), getattr(reference, name), name)
    assert table.spacing == reference.spacing and table.fuzzy == reference.fuzzy
    assert table.to_dict() == reference.to_dict()

    partial = nr.OverlapTable.from_sums(
        labels, vol, None, None, p, q, spacing=spacing_itk, fuzzy=fuzzy, skipped_labels=(9,)
    )
    assert np.isnan(partial.complexity).all() and np.isnan(partial.target_overlap).all()
    assert partial.skipped_labels == (9,)
    assert partial.generalized("inverse_volume") == reference.generalized("inverse_volume")
    with pytest.raises(ValueError, match="built with complexity=False"):
        partial.generalized("complexity")
    with pytest.raises(ValueError, match=r"gradient_sums has shape \(5, 2\), expected \(5, 3\)"):
        nr.OverlapTable.from_sums(
            labels, vol, None, grad[:, :2], p, q, spacing=spacing_itk, fuzzy=fuzzy
        )
    with pytest.raises(ValueError, match="do not agree on"):
        nr.OverlapTable.from_sums(labels, vol, None, None, p[:2], q, spacing=(1, 1, 1), fuzzy=0)


# -- command line ----------------------------------------------------------------------------


def _write(path, arr, spacing=(1.0, 1.0, 1.0)):
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing)
    sitk.WriteImage(img, str(path))
    return str(path)


def _assert_one_line_error(capsys, code, *fragments):
    out = capsys.readouterr()
    assert code == 2
    lines = out.err.strip().splitlines()
    assert len(lines) == 1, out.err
    assert "Traceback" not in out.err
    for frag in fragments:
        assert frag in lines[0]


def test_cli_prints_and_writes_tables(rng, tmp_path, capsys):
    crisp = _smooth_crisp(rng, 4, (5, 6, 7), 4).astype(np.uint8)
    paths = [_write(tmp_path / f"l{i}.mha", a, (0.8, 1.0, 2.0)) for i, a in enumerate(crisp)]
    csv_path, json_path = tmp_path / "t.csv", tmp_path / "o.json"
    code = main(["overlap", *paths, "--table", str(csv_path), "--json", str(json_path)])
    out = capsys.readouterr().out
    assert code == 0
    ref = _brute(_one_hot(crisp, [1, 2, 3]), spacing_np=(2.0, 1.0, 0.8))
    data = json.loads(json_path.read_text())
    for w in WEIGHTINGS:
        assert data["generalized"][w] == pytest.approx(ref["generalized"][w], rel=1e-12)
        assert f"{w} " in out
    rows = csv_path.read_text().splitlines()
    assert rows[0].startswith("label,volume,complexity,jaccard,dice,target_overlap,weight_volume")
    assert [int(r.split(",")[0]) for r in rows[1:]] == [1, 2, 3]
    jac = [float(r.split(",")[3]) for r in rows[1:]]
    np.testing.assert_allclose(jac, ref["jaccard"], rtol=1e-12)

    code = main(["overlap", *paths, "--weighting", "complexity", "--weighting", "volume"])
    out = capsys.readouterr().out
    assert code == 0 and "complexity" in out and "inverse_volume" not in out


def test_cli_label_maps_on_different_grids(rng, tmp_path, capsys):
    a = _write(tmp_path / "a.nii.gz", np.ones((4, 5, 6), np.uint8))
    b = _write(tmp_path / "b.nii.gz", np.ones((4, 5, 6), np.uint8), spacing=(1.0, 2.0, 1.0))
    out_json = tmp_path / "o.json"
    code = main(["overlap", a, b, "--json", str(out_json), "--table", str(tmp_path / "t.csv")])
    _assert_one_line_error(capsys, code, "b.nii.gz", "not on the grid of", "spacing")
    assert not out_json.exists() and not (tmp_path / "t.csv").exists()


def test_cli_non_integer_values_passed_as_crisp(tmp_path, capsys):
    a = _write(tmp_path / "a.nrrd", np.ones((3, 4, 5), np.float32))
    b = _write(tmp_path / "b.nrrd", np.full((3, 4, 5), 0.25, np.float32))
    out_json = tmp_path / "o.json"
    code = main(["overlap", a, b, "--json", str(out_json)])
    _assert_one_line_error(capsys, code, "b.nrrd", "non-integer values in a crisp label map")
    assert not out_json.exists()


def test_cli_empty_sets(tmp_path, capsys):
    zeros = [_write(tmp_path / f"z{i}.nii.gz", np.zeros((3, 4, 5), np.uint8)) for i in range(3)]
    out_json = tmp_path / "o.json"
    code = main(["overlap", *zeros, "--json", str(out_json)])
    _assert_one_line_error(capsys, code, "z0.nii.gz", "no label other than background 0")
    code = main(["overlap", zeros[0], "--json", str(out_json)])
    _assert_one_line_error(capsys, code, "need at least 2")
    code = main(["overlap", str(tmp_path / "missing.nii.gz"), zeros[0]])
    _assert_one_line_error(capsys, code, "missing.nii.gz", "not found")
    assert not out_json.exists()
    assert list(tmp_path.glob(".o.tmp-*")) == []
