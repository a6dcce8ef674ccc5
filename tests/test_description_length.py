"""The description length's numerics against direct computations (issue 41).

The frequency-domain sums (:class:`SpectrumSums`) against residuals formed voxel by voxel
and coded frequency by frequency; the jackknife against the group recomputed without the
subject; the affine part against a fit in physical coordinates on an oblique, anisotropic
grid; Otsu against SimpleITK's; the noise estimate against known noise.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from itk_nrreval.measures.description_length import (
    DescriptionLength,
    SpectrumSums,
    gaussian_rate,
    group_bits,
    left_out_bits,
    noise_and_gradient,
    non_linear_part,
    otsu_threshold,
    z_of_difference,
)
from itk_nrreval.report.evaluation_text import results_csv


def _direct_bits(signals: np.ndarray, mask: np.ndarray, distortion: float) -> float:
    """The group's bits the long way: residuals from the mean image voxel by voxel, each
    frequency's average power coded by its own log, plus the template."""
    n = mask.sum()
    fraction = n / mask.size
    mean = signals.mean(axis=0)
    powers = np.zeros(mask.shape)
    for x in signals:
        powers += np.abs(np.fft.fftn(np.where(mask, x - mean, 0.0))) ** 2
    powers /= len(signals) * n
    template = np.where(mask, mean - mean[mask].mean(), 0.0)
    template_power = np.abs(np.fft.fftn(template)) ** 2 / n
    bits = 0.0
    for p, t in zip(powers.ravel(), template_power.ravel(), strict=True):
        if p > distortion:
            bits += len(signals) * fraction * 0.5 * math.log2(p / distortion)
        if t > distortion:
            bits += fraction * 0.5 * math.log2(t / distortion)
    return bits


def _sums(signals, mask):
    sums = SpectrumSums(mask.shape)
    for x in signals:
        sums.add(np.fft.fftn(np.where(mask, x, 0.0)))
    return sums


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(3, 8),
    shape=st.sampled_from([(9, 12), (6, 7, 5)]),
    distortion=st.floats(0.05, 3.0),
    seed=st.integers(0, 2**16),
)
def test_group_and_left_out_bits_match_the_direct_computation(n, shape, distortion, seed):
    rng = np.random.default_rng(seed)
    mask = rng.random(shape) > 0.3
    mask.flat[0] = True
    signals = rng.normal(size=(n, *shape)) * rng.uniform(0.2, 3.0)
    signals += np.linspace(0, 2, signals[0].size).reshape(shape)  # a shared structure
    mask_spectrum = np.fft.fftn(mask.astype(float))
    sums = _sums(signals, mask)
    assert math.isclose(
        group_bits(sums, mask_spectrum, distortion),
        _direct_bits(signals, mask, distortion),
        rel_tol=1e-9,
        abs_tol=1e-9,
    )
    j = int(rng.integers(n))
    left_out = np.delete(signals, j, axis=0)
    spectrum = np.fft.fftn(np.where(mask, signals[j], 0.0))
    assert math.isclose(
        left_out_bits(sums, spectrum, mask_spectrum, distortion),
        _direct_bits(left_out, mask, distortion),
        rel_tol=1e-9,
        abs_tol=1e-9,
    )


def test_gaussian_rate_of_white_noise_is_half_the_log_of_its_power_ratio():
    rng = np.random.default_rng(0)
    shape = (128, 128)
    for ratio in (4.0, 16.0, 100.0):
        x = rng.normal(0, math.sqrt(ratio), size=(20, *shape))
        power = np.mean(np.abs(np.fft.fftn(x, axes=(1, 2))) ** 2, axis=0) / x[0].size
        per_voxel = gaussian_rate(power, 1.0, fraction=1.0) / x[0].size
        assert abs(per_voxel - 0.5 * math.log2(ratio)) < 0.02
    # below the distortion nothing is coded
    assert gaussian_rate(np.full(shape, 0.5), 1.0, fraction=1.0) == 0.0


def test_fitting_noise_buys_no_texture_bits():
    """Residuals of white noise below the noise level cost nothing, however small."""
    rng = np.random.default_rng(1)
    mask = np.ones((64, 64), bool)
    m = np.fft.fftn(mask.astype(float))
    quiet = _sums(rng.normal(0, 0.3, size=(12, 64, 64)), mask)
    quieter = _sums(rng.normal(0, 0.1, size=(12, 64, 64)), mask)
    assert group_bits(quiet, m, 1.0) == group_bits(quieter, m, 1.0) == 0.0


def test_non_linear_part_removes_an_affine_map_of_physical_points_on_an_oblique_grid():
    size, spacing = (11, 9, 7), (1.5, 0.8, 2.5)  # ITK order
    image = sitk.Image(size, sitk.sitkUInt8)
    image.SetSpacing(spacing)
    image.SetOrigin((10.0, -4.0, 3.0))
    angle = 0.4
    c, s = math.cos(angle), math.sin(angle)
    image.SetDirection((c, -s, 0.0, s * 0.8, c * 0.8, -0.6, s * 0.6, c * 0.6, 0.8))
    points = np.array(
        [
            image.TransformIndexToPhysicalPoint((i, j, k))
            for k in range(size[2])
            for j in range(size[1])
            for i in range(size[0])
        ]
    ).reshape(size[2], size[1], size[0], 3)
    rng = np.random.default_rng(2)
    a, t = rng.normal(size=(3, 3)), rng.normal(size=3)
    affine = points @ a.T + t
    bump = np.zeros_like(affine)
    bump[4:7, 3:6, 4:8, 0] = 1.0
    mask = np.zeros(points.shape[:3], bool)
    mask[1:6, 1:8, 2:10] = True
    numpy_spacing = spacing[::-1]
    assert np.abs(non_linear_part(affine, mask, numpy_spacing)).max() < 1e-9
    # the bump keeps what no affine map of physical points explains
    design = np.concatenate([points[mask], np.ones((mask.sum(), 1))], axis=1)
    coef, *_ = np.linalg.lstsq(design, bump[mask], rcond=None)
    flat = np.concatenate([points.reshape(-1, 3), np.ones((points[..., 0].size, 1))], 1)
    expected = bump - (flat @ coef).reshape(bump.shape)
    np.testing.assert_allclose(
        non_linear_part(affine + bump, mask, numpy_spacing), expected, atol=1e-9
    )


def test_otsu_threshold_splits_as_simpleitk_does():
    rng = np.random.default_rng(3)
    image = rng.gamma(2.0, 20.0, size=(40, 50, 30))
    image[10:30, 15:35, 5:25] += 250
    ours = image > otsu_threshold(image)
    theirs = sitk.GetArrayFromImage(sitk.OtsuThreshold(sitk.GetImageFromArray(image), 0, 1))
    assert np.mean(ours != theirs.astype(bool)) < 0.005


def test_noise_and_gradient_of_a_smooth_image_with_known_noise():
    # (sharp edges bias the noise estimate up: by 16% in 3D where this image is cut at 100)
    rng = np.random.default_rng(4)
    for shape, spacing in (((160, 150), (1.0, 1.0)), ((48, 60, 40), (2.5, 1.0, 1.5))):
        clean = ndimage.gaussian_filter(rng.normal(size=shape), 4) * 2000 + 100
        sigma, g2 = noise_and_gradient(clean + rng.normal(0, 3.0, shape), spacing)
        _, clean_g2 = noise_and_gradient(clean, spacing)
        assert abs(sigma - 3.0) < 0.3
        assert abs(g2 - clean_g2) < 0.15 * clean_g2


def test_z_of_difference_is_the_paired_jackknife():
    def dl(bits, jack):
        return DescriptionLength(bits, bits, 0.0, tuple(jack), 1.0, 1.0)

    a = dl(100.0, [99.0, 101.0, 100.5, 99.5])
    b = dl(110.0, [108.0, 112.0, 110.0, 109.0])
    d = np.array(b.jackknife) - np.array(a.jackknife)
    stderr = math.sqrt(3 / 4 * np.sum((d - d.mean()) ** 2))
    assert math.isclose(z_of_difference(a, b), 10.0 / stderr)
    assert math.isclose(z_of_difference(b, a), -10.0 / stderr)
    assert DescriptionLength.from_dict(a.to_dict()) == a


def _read_transform(path) -> sitk.Transform:
    """A transform file, or a displacement-field image as its transform."""
    if str(path).endswith((".nii.gz", ".nii", ".mha", ".nrrd")):
        field = sitk.Cast(sitk.ReadImage(str(path)), sitk.sitkVectorFloat64)
        return sitk.DisplacementFieldTransform(field)
    return sitk.ReadTransform(str(path))


def _direct_parts(images, fields, region, precisions) -> tuple[float, float]:
    """Texture and shape bits of a group, each coded directly (:func:`_direct_bits`)."""
    texture = _direct_bits(images, region, precisions[0])
    dims = range(fields.shape[-1])
    return texture, sum(_direct_bits(fields[..., c], region, precisions[1]) for c in dims)


def test_evaluate_reports_the_description_length_of_the_exported_images_and_fields(tmp_path):
    """Oblique, anisotropic 3D images not co-located with their reference: each
    registration's description length equals the one coded directly (:func:`_direct_bits`)
    from the exported resampled images and from its transforms' displacements on the common
    grid sampled by SimpleITK (F, then T_i); one left-out subject likewise."""
    import warnings

    from test_orientation import make_moved_masked_case_3d

    import itk_nrreval as nr
    from itk_nrreval.io.manifest import load_manifest

    folder = make_moved_masked_case_3d(tmp_path)
    cache = tmp_path / "cache"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = nr.evaluate(
            folder / "manifest.yaml",
            n_samples=1000,
            confidence=False,
            progress=False,
            description_length=True,
            execution=nr.Execution(cache=cache, keep_resampled=True),
        )
    assert result.to_dict()["options"]["description_length"] is True
    rows = list(csv.DictReader(io.StringIO(results_csv(result))))
    for row in rows:
        dl = result.scores[row["registration"]].description_length
        assert float(row["description_length_bits"]) == pytest.approx(dl.bits)
    out = nr.export_resampled(result, tmp_path / "resampled", cache=cache)
    region_image = sitk.ReadImage(str(out / "region.nii.gz"))
    region = sitk.GetArrayFromImage(region_image) > 0
    assert 0.1 < region.mean() < 1.0
    spacing = region_image.GetSpacing()[::-1]
    m = load_manifest(folder / "manifest.yaml")
    for name, scores in result.scores.items():
        dl = scores.description_length
        n = len(m.images)
        images = np.stack(
            [
                sitk.GetArrayFromImage(sitk.ReadImage(str(out / name / f"image_{i:03d}.nii.gz")))
                for i in range(n)
            ]
        ).astype(float)
        fields = []
        for chain in m.registrations[name].transforms:
            composite = sitk.CompositeTransform(3)
            for t in chain[::-1]:  # SimpleITK applies the last added first
                composite.AddTransform(_read_transform(t))
            composite.AddTransform(scores.frame.transform)  # F acts first
            to_field = sitk.TransformToDisplacementFieldFilter()
            to_field.SetReferenceImage(region_image)
            field = sitk.GetArrayFromImage(to_field.Execute(composite))
            fields.append(non_linear_part(field, region, spacing))
        fields = np.stack(fields)
        precisions = (dl.noise_sd**2, dl.displacement_precision_mm**2)
        texture, shape = _direct_parts(images, fields, region, precisions)
        # the cache holds the resampled images in float32
        assert dl.texture == pytest.approx(texture / n, rel=1e-4)
        assert dl.shape == pytest.approx(shape / n, rel=1e-4, abs=1e-6)
        left = sum(_direct_parts(images[1:], fields[1:], region, precisions)) / (n - 1)
        assert dl.jackknife[0] == pytest.approx(left, rel=1e-4)
    # the truth's description length is shorter than the identity's (no shape, worse texture)
    assert result.scores["truth"].description_length.texture < (
        result.scores["identity"].description_length.texture
    )
