"""nrreval register: real engines on a small 2D population with known correspondence.

The population is a smooth brain-like phantom warped by known transforms (random affine and
a smooth displacement of up to 4 mm), so the true correspondence error of any registration
can be measured: for each reference point p, the template points ``S_i(R_i(p))`` of all
images should coincide (``S_i`` maps image i's points to the template, ``R_i`` is the
registration's reference -> image transform).
"""

from __future__ import annotations

import dataclasses
import json
import sys

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.ndimage import gaussian_filter

from itk_nrreval import InputError, RegistrationResult, register
from itk_nrreval.cli import main
from itk_nrreval.experiments.registration import AffineOptions, EngineError, FluidOptions
from itk_nrreval.experiments.registration._elastix_worker import ElastixWorker, elastix_worker_for
from itk_nrreval.experiments.registration.bspline import sitk_bspline
from itk_nrreval.experiments.registration.fluid import (
    ants_syn,
    demons_register,
    seeded_ants_registration,
)
from itk_nrreval.io.manifest import load_manifest
from itk_nrreval.io.transforms import chain_transform, read_transform

try:
    import ants
except ImportError:  # the ANTs tests skip, saying so
    ants = None
needs_ants = pytest.mark.skipif(
    ants is None, reason="antspyx is not installed (pip install itk-nrreval[ants])"
)

N_IMAGES, SIZE = 6, 96


def _template(n: int) -> sitk.Image:
    yy, xx = (np.mgrid[:n, :n] + 0.5) / n - 0.5

    def ell(cx, cy, rx, ry):
        return ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1

    img = np.zeros((n, n))
    for (cx, cy, rx, ry), value in [
        ((0, 0, 0.40, 0.45), 1.0),  # skull
        ((0, 0, 0.36, 0.41), 0.35),  # CSF
        ((0, 0, 0.33, 0.38), 0.7),  # grey matter
        ((0, 0.02, 0.24, 0.29), 1.0),  # white matter
        ((-0.08, -0.02, 0.05, 0.12), 0.2),  # ventricles
        ((0.08, -0.02, 0.05, 0.12), 0.2),
        ((0, 0.2, 0.06, 0.04), 0.5),
        ((-0.15, 0.18, 0.04, 0.05), 0.45),
        ((0.17, -0.2, 0.05, 0.04), 0.55),
    ]:
        img[ell(cx, cy, rx, ry)] = value
    return sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(img.astype(np.float32)), 1.0)


def _population(n_images: int, size: int, seed: int):
    """Images and their true transforms image point -> template point."""
    rng = np.random.default_rng(seed)
    template = _template(size)
    images, truths = [], []
    for _ in range(n_images):
        angle, scale = rng.uniform(-0.12, 0.12), rng.uniform(0.92, 1.08, 2)
        c, s = np.cos(angle), np.sin(angle)
        affine = sitk.AffineTransform(2)
        affine.SetMatrix(tuple((np.array([[c, -s], [s, c]]) @ np.diag(scale)).ravel()))
        affine.SetCenter((size / 2 - 0.5,) * 2)
        affine.SetTranslation(tuple(rng.uniform(-4, 4, 2)))
        noise = rng.standard_normal((2, size, size))
        disp = np.stack([gaussian_filter(noise[k], 10) for k in range(2)], axis=-1)
        disp *= 4.0 / np.abs(disp).max()
        warp = sitk.DisplacementFieldTransform(sitk.GetImageFromArray(disp, isVector=True))
        truth = sitk.CompositeTransform([affine, warp])
        images.append(sitk.Resample(template, template, truth, sitk.sitkLinear, 0.0))
        truths.append(truth)
    return images, truths


def correspondence_error(transforms, reference: sitk.Image, truths, margin: float = 0.15) -> float:
    """Mean distance (mm) of each image's template point from the group's mean one."""
    points = []
    for t, s in zip(transforms, truths, strict=True):
        field = sitk.TransformToDisplacementField(
            sitk.CompositeTransform([s, t]),  # s(t(p))
            sitk.sitkVectorFloat64,
            reference.GetSize(),
            reference.GetOrigin(),
            reference.GetSpacing(),
            reference.GetDirection(),
        )
        points.append(sitk.GetArrayFromImage(field))  # displacement from the same p for all
    pts = np.stack(points)
    m = int(margin * reference.GetSize()[0])
    pts = pts[:, m:-m, m:-m]
    return float(np.linalg.norm(pts - pts.mean(axis=0), axis=-1).mean())


@pytest.fixture(scope="module")
def population():
    return _population(N_IMAGES, SIZE, seed=1)


@pytest.fixture(scope="module")
def affine_result(population):
    images, _ = population
    return register(images, method="affine", progress=False)


@pytest.fixture(scope="module")
def worker(elastix_worker):
    return elastix_worker  # the session's (conftest.py): itk-elastix loaded once


def _identity(n):
    return [sitk.Transform(2, sitk.sitkIdentity)] * n


def _interior(image: sitk.Image, margin: int = 8) -> np.ndarray:
    return sitk.GetArrayFromImage(image)[margin:-margin, margin:-margin]


def _check_written(result: RegistrationResult, tmp_path, images, *, stepwise=False) -> None:
    """The .h5 files read back reproduce the engine's own resampled images.

    With `stepwise`, each image is resampled through the read-back composite's transforms
    one at a time, first to last (``[A, B]``: through ``A``, then through ``B``), as an
    engine that registers pre-resampled images did.
    """
    paths = result.write(tmp_path)
    assert len(paths["transforms"]) == len(images)
    reference = sitk.ReadImage(str(paths["reference"]))
    for img, path, engine_out in zip(images, paths["transforms"], result.resampled, strict=True):
        back = sitk.ReadTransform(str(path))
        if stepwise:
            mine = img
            for k in range(back.GetNumberOfTransforms()):
                mine = sitk.Resample(
                    mine, reference, back.GetNthTransform(k), sitk.sitkLinear, 0.0, sitk.sitkFloat32
                )
        else:
            mine = sitk.Resample(img, reference, back, sitk.sitkLinear, 0.0, sitk.sitkFloat32)
        diff = np.abs(_interior(mine) - _interior(engine_out))
        assert diff.max() < 1e-3, f"{path.name}: max difference {diff.max()}"


def test_affine_improves_over_identity(population, affine_result):
    images, truths = population
    before = correspondence_error(_identity(N_IMAGES), affine_result.reference, truths)
    after = correspondence_error(affine_result.transforms, affine_result.reference, truths)
    assert after < 0.6 * before
    assert affine_result.reference_index is not None
    ref = affine_result.reference_index
    assert isinstance(affine_result.transforms[ref], sitk.AffineTransform)
    assert np.allclose(affine_result.transforms[ref].GetParameters(), [1, 0, 0, 1, 0, 0])


def test_the_same_seed_gives_the_same_transforms(population):
    # SimpleITK reads a sampling seed of 0 as "seed from the wall clock": image 0 of a run
    # with seed 0 (the default) was registered differently every time.
    images, _ = population
    runs = [
        register(images[:3], method="affine", reference=1, seed=0, progress=False) for _ in range(2)
    ]
    for a, b in zip(*(r.transforms for r in runs), strict=True):
        np.testing.assert_array_equal(a.GetParameters(), b.GetParameters())
    # The same for SimpleITK's B-spline registration.
    params = [
        sitk_bspline(
            images[1],
            images[0],
            initial=sitk.AffineTransform(2),
            grid_spacing=24.0,
            levels=1,
            iterations=5,
            sampling=0.2,
            seed=0,
        ).GetParameters()
        for _ in range(2)
    ]
    np.testing.assert_array_equal(*params)


def test_reference_choice_near_and_far_differ(population):
    images, _ = population
    near = register(images, method="affine", reference_choice="near-mean", progress=False)
    far = register(images, method="affine", reference_choice="far-from-mean", progress=False)
    assert near.reference_index != far.reference_index
    assert near.settings["reference_choice"] == "near-mean"


def test_fluid_improves_over_affine_and_order_is_affine_after_field(
    population, affine_result, tmp_path
):
    images, truths = population
    fluid = register(images, method="fluid", progress=False)
    assert fluid.reference_index == affine_result.reference_index
    ref = fluid.reference
    assert correspondence_error(fluid.transforms, ref, truths) < 0.8 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    # [A, D] maps p to A(D(p)); the other order registers worse.
    i = (fluid.reference_index + 1) % N_IMAGES
    affine, field = fluid.transforms[i].GetNthTransform(0), fluid.transforms[i].GetNthTransform(1)
    assert isinstance(affine.Downcast(), sitk.AffineTransform)
    ref_arr = _interior(ref)

    def mse(t):
        return float(((_interior(sitk.Resample(images[i], ref, t)) - ref_arr) ** 2).mean())

    assert mse(sitk.CompositeTransform([affine, field])) < 0.5 * mse(
        sitk.CompositeTransform([field, affine])
    )
    _check_written(fluid, tmp_path, images)


def test_an_earlier_affine_stage_is_reused(population, affine_result):
    images, truths = population
    fluid = register(images, method="fluid", affine=affine_result, progress=False)
    assert fluid.reference_index == affine_result.reference_index
    assert fluid.settings["affine_stage"] == "reused"
    for t, a in zip(fluid.transforms, affine_result.transforms, strict=True):
        first = t.GetNthTransform(0) if t.GetName() == "CompositeTransform" else t
        np.testing.assert_array_equal(first.GetParameters(), a.GetParameters())
    ref = fluid.reference
    assert correspondence_error(fluid.transforms, ref, truths) < 0.8 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    with pytest.raises(InputError, match="affine: its reference is used"):
        register(images, method="fluid", affine=affine_result, reference=0, progress=False)
    with pytest.raises(InputError, match="affine: expected an affine registration"):
        register(images, method="pairwise", affine=fluid, progress=False)


def test_out_writes_the_result_and_its_settings(population, tmp_path):
    """``register(out=...)`` writes what ``result.write`` does; registration.json holds the
    settings (in this order: the file's layout), the reference index, time and file names."""
    images, _ = population
    paths = []
    for i, img in enumerate(images[:3]):
        paths.append(str(tmp_path / f"s{i}.nii.gz"))
        sitk.WriteImage(img, paths[-1])
    out = tmp_path / "affine"
    result = register(
        paths, method="affine", reference_choice="far-from-mean", seed=5, out=out, progress=False
    )
    defaults = dataclasses.asdict(AffineOptions())
    settings = {
        "method": "affine",
        "engine": "simpleitk",
        "seed": 5,
        "n_images": 3,
        "images": paths,
        "reference_choice": "far-from-mean",
        "affine_options": defaults,
        "affine_stage": "computed",
        "options": defaults,
    }
    assert list(result.settings.items()) == list(settings.items())
    transforms = [f"{i:03d}_image{i:03d}.h5" for i in range(3)]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [".nrreval-output.json", "reference.nii.gz", "registration.json", *transforms]
    )  # the first: the record of what the toolkit wrote (replaced by a rerun, nothing else)
    log = json.loads((out / "registration.json").read_text())
    assert list(log) == [
        *settings,
        "reference_index",
        "seconds",
        "reference",
        "transforms",
        "convention",
    ]
    assert {k: log[k] for k in settings} == json.loads(json.dumps(settings))
    assert log["reference_index"] == result.reference_index is not None
    assert log["transforms"] == transforms and log["reference"] == "reference.nii.gz"
    # A reused affine stage records the affine's reference choice, and that it was reused.
    reused = register(paths, method="affine", affine=result, progress=False)
    assert reused.settings["reference_choice"] == "far-from-mean"
    assert reused.settings["affine_stage"] == "reused"
    assert reused.reference_index == result.reference_index


def test_pairwise_simpleitk_improves_over_affine(population, affine_result, tmp_path):
    images, truths = population
    result = register(
        images, method="pairwise", engine="simpleitk", options={"iterations": 30}, progress=False
    )
    ref = result.reference
    assert correspondence_error(result.transforms, ref, truths) < 0.8 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    _check_written(result, tmp_path, images)


@pytest.mark.parametrize("engine", ["elastix", "simpleitk"])
def test_groupwise_improves_over_affine(population, affine_result, worker, tmp_path, engine):
    images, truths = population
    result = register(
        images, method="groupwise", engine=engine, elastix_worker=worker, progress=False
    )
    assert result.engine == engine
    assert result.reference_index is None
    ref = result.reference
    assert correspondence_error(result.transforms, ref, truths) < 0.85 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    _check_written(result, tmp_path, images)


def test_groupwise_elastix_stack_improves_and_matches_its_own_resampling(
    population, affine_result, worker, tmp_path
):
    images, truths = population
    result = register(
        images,
        method="groupwise",
        engine="elastix-stack",
        affine=affine_result,
        options={"elastix_iterations": 150},
        elastix_worker=worker,
        progress=False,
    )
    assert result.engine == "elastix-stack" and result.reference_index is None
    ref = result.reference
    assert ref.GetSize() == affine_result.reference.GetSize()
    assert correspondence_error(result.transforms, ref, truths) < 0.85 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    # Every transform is [A_i, B_i] with elastix's sub-transform i as B_i: resampling the
    # image through A_i, then B_i, gives elastix's own registered slice i.
    for t, a in zip(result.transforms, affine_result.transforms, strict=True):
        assert t.GetNumberOfTransforms() == 2
        np.testing.assert_array_equal(t.GetNthTransform(0).GetParameters(), a.GetParameters())
        assert isinstance(t.GetNthTransform(1).Downcast(), sitk.BSplineTransform)
    _check_written(result, tmp_path, images, stepwise=True)
    # elastix's metric keeps the group's mean deformation at zero.
    coefficients = np.array([t.GetNthTransform(1).GetParameters() for t in result.transforms])
    assert np.abs(coefficients).max() > 1.0
    assert np.abs(coefficients.mean(axis=0)).max() < 1e-6


def test_groupwise_elastix_stack_refuses_3d():
    images = [sitk.Image([8, 8, 8], sitk.sitkFloat32) for _ in range(2)]
    with pytest.raises(InputError, match=r"elastix-stack supports 2D images only, got 3D"):
        register(
            images,
            method="groupwise",
            engine="elastix-stack",
            elastix_worker=worker,
            progress=False,
        )


def test_pairwise_elastix_improves_and_matches_its_own_resampling(
    population, affine_result, worker, tmp_path
):
    images, truths = population
    result = register(images, method="pairwise", elastix_worker=worker, progress=False)
    assert result.engine == "elastix"
    ref = result.reference
    assert correspondence_error(result.transforms, ref, truths) < 0.8 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    _check_written(result, tmp_path, images)  # .h5 fields vs elastix's own result images


def test_elastix_bad_parameters_give_a_clear_error(population, worker):
    images, _ = population
    with pytest.raises(EngineError, match=r"elastix failed on image \d+: .*NoSuchTransform"):
        register(
            images[:2],
            method="pairwise",
            reference=0,
            options={"elastix_parameters": {"Transform": "NoSuchTransform"}},
            elastix_worker=worker,
            progress=False,
        )
    assert worker.alive  # a refused job does not kill the worker


def test_elastix_crash_gives_a_clear_error(population):
    images, _ = population
    with ElastixWorker() as crashing:
        with pytest.raises(
            EngineError, match=r"worker process died \(signal 6\) while registering a test job"
        ):
            crashing.request({"op": "abort"}, what="a test job")
        with pytest.raises(
            EngineError, match=r"worker process died \(signal 6\) while registering image 1"
        ):
            register(
                images[:2], method="pairwise", reference=0, elastix_worker=crashing, progress=False
            )


def test_a_worker_is_started_for_the_block_only_when_none_is_given(worker):
    """elastix_worker_for: the caller's worker is used and left running; without one, a
    worker is started and stopped (its folder removed) when the block ends, also on error."""
    with elastix_worker_for(worker) as used:
        assert used is worker
    assert worker.alive
    with elastix_worker_for(None, needed=False) as used:
        assert used is None
    with pytest.raises(EngineError, match="the job failed"):
        with elastix_worker_for(None) as started:
            assert isinstance(started, ElastixWorker) and started.alive
            raise EngineError("the job failed")
    assert not started.alive and not started.directory.exists()


def test_missing_ants_is_a_clear_input_error(population, monkeypatch):
    # Runs with or without antspyx: a None entry in sys.modules makes `import ants` fail.
    monkeypatch.setitem(sys.modules, "ants", None)
    images, _ = population
    with pytest.raises(InputError, match=r"antspyx is not installed: pip install antspyx"):
        register(images, method="fluid", engine="ants", progress=False)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"method": "rigid"}, r"method: 'rigid' is not one of 'affine', 'fluid'"),
        ({"method": "affine", "engine": "elastix"}, r"engine for method 'affine': 'elastix'"),
        (
            {"method": "groupwise", "reference": 0},
            r"groupwise registers to the evolving group mean",
        ),
        (
            {"method": "fluid", "options": {"iters": 3}},
            r"fluid options: unknown 'iters' \(accepted:",
        ),
        ({"method": "affine", "reference_choice": "median"}, r"reference_choice: 'median'"),
        # The smoothing was in "voxels" before it was in mm: the old name is refused.
        (
            {"method": "fluid", "options": {"smoothing_sigma": 2.5}},
            r"fluid options: unknown 'smoothing_sigma' \(accepted: .*smoothing_mm",
        ),
        (
            {"method": "fluid", "options": {"smoothing_mm": [4.0, 2.0]}},
            r"smoothing_mm gives 2 values for 3 levels",
        ),
        (
            {"method": "pairwise", "engine": "simpleitk", "options": {"bending_weight": 1.0}},
            r"pairwise options: bending_weight needs the elastix engine, not 'simpleitk'",
        ),
        (
            {"method": "pairwise", "options": {"bending_weight": -0.5}},
            r"bending_weight must be a number >= 0, got -0.5",
        ),
        (
            {"method": "fluid", "options": {"update_smoothing_mm": -1.0}},
            r"update_smoothing_mm must be a finite number >= 0 \(mm\), got -1.0",
        ),
        (
            {"method": "fluid", "options": {"smoothing_mm": float("nan")}},
            r"smoothing_mm must be finite numbers > 0 \(mm\), got nan",
        ),
        ({"method": "affine", "reference": 9}, r"reference: index 9 out of range for 6 images"),
    ],
)
def test_bad_arguments(population, kwargs, message):
    images, _ = population
    with pytest.raises(InputError, match=message):
        register(images, progress=False, **kwargs)


def test_cli_register_writes_transforms_reference_log_and_manifest(population, tmp_path):
    images, _ = population
    paths = []
    for i, img in enumerate(images):
        paths.append(str(tmp_path / f"s{i:02d}.nii.gz"))
        sitk.WriteImage(img, paths[-1])
    out = tmp_path / "affine"
    code = main(
        [
            "register",
            "--images",
            *paths,
            "--method",
            "affine",
            "--out",
            str(out),
            "--reference",
            paths[2],
            "--no-progress",
        ]
    )
    assert code == 0
    manifest = load_manifest(tmp_path / "manifest.yaml")
    reg = manifest.registrations["affine"]
    assert reg.reference_index == 2
    assert len(reg.transforms) == N_IMAGES
    assert (out / "registration.json").is_file() and (out / "reference.nii.gz").is_file()
    t = sitk.ReadTransform(str(reg.transforms[0][0]))
    assert t.GetDimension() == 2


def test_cli_missing_engine_is_one_line_exit_2(population, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ants", None)  # antspyx unimportable, installed or not
    path = tmp_path / "a.nii.gz"
    sitk.WriteImage(population[0][0], str(path))
    code = main(
        [
            "register",
            "--images",
            str(path),
            str(path),
            "--method",
            "fluid",
            "--engine",
            "ants",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code == 2
    err = capsys.readouterr().err
    assert "antspyx is not installed: pip install antspyx" in err and "Traceback" not in err


# --------------------------------------------------------------------------------------------
# Demons smoothing units. ITK's demons filters take the smoothing standard deviations in
# pixels ("The values are set with respect to pixel coordinates"); FluidOptions states them in
# mm. An impulse measures the smoothing directly: a linear ramp and the same ramp with one
# voxel raised differ only at that voxel, so one demons iteration produces an update at that
# voxel alone (far below a voxel, so its exponential is itself), and the displacement field
# is that update convolved with the smoothing kernel. Its width along each axis, in mm, is the
# smoothing actually applied.


def _impulse_pair(spacing, size):
    grid = sitk.Image(list(size), sitk.sitkFloat32)
    grid.SetSpacing(list(spacing))
    y, x = np.meshgrid(
        np.arange(size[1]) * spacing[1], np.arange(size[0]) * spacing[0], indexing="ij"
    )
    ramp = (0.1 * x + 0.07 * y).astype(np.float32)
    raised = ramp.copy()
    raised[size[1] // 2, size[0] // 2] += 0.02
    fixed, moving = sitk.GetImageFromArray(ramp), sitk.GetImageFromArray(raised)
    fixed.CopyInformation(grid)
    moving.CopyInformation(grid)
    return fixed, moving


def _kernel_widths_mm(field: sitk.Image) -> np.ndarray:
    """Standard deviation (mm) along x and y of the field's x component (one-signed)."""
    w = sitk.GetArrayFromImage(field)[..., 0]
    assert np.all(w <= 0) or np.all(w >= 0)
    out = []
    for axis, profile in enumerate((w.sum(axis=0), w.sum(axis=1))):  # along x, along y
        pos = np.arange(profile.size) * field.GetSpacing()[axis]
        mean = (profile * pos).sum() / profile.sum()
        out.append(np.sqrt((profile * (pos - mean) ** 2).sum() / profile.sum()))
    return np.array(out)


def _one_iteration(**fields) -> FluidOptions:
    return FluidOptions(shrink_factors=(1,), iterations=(1,), **fields)


@pytest.mark.parametrize(
    ("spacing", "size"),
    [
        ((1.0, 1.0), (64, 64)),
        ((1.0, 2.0), (64, 64)),
        ((2.0, 2.0), (64, 64)),
        ((0.25, 0.5), (160, 96)),
    ],
)
def test_demons_smoothing_is_the_stated_mm_on_every_axis(spacing, size):
    # 3 mm is 12 pixels at 0.25 mm: a kernel wider than ITK's default 30 coefficients a side.
    field = demons_register(*_impulse_pair(spacing, size), options=_one_iteration(smoothing_mm=3.0))
    np.testing.assert_allclose(_kernel_widths_mm(field), [3.0, 3.0], rtol=0.02)


@pytest.mark.parametrize("spacing", [(1.0, 1.0), (1.0, 2.0)])
def test_demons_update_smoothing_adds_in_quadrature_in_mm(spacing):
    # One iteration from a zero field: the impulse's update is smoothed by the update kernel,
    # then the field by the field kernel; two Gaussians compose into sqrt(u^2 + s^2).
    pair = _impulse_pair(spacing, (64, 64))
    field = demons_register(
        *pair, options=_one_iteration(smoothing_mm=3.0, update_smoothing_mm=2.0)
    )
    np.testing.assert_allclose(_kernel_widths_mm(field), [np.hypot(3.0, 2.0)] * 2, rtol=0.03)
    # 0 (the default) leaves the update alone: the field kernel alone.
    unsmoothed = demons_register(*pair, options=_one_iteration(smoothing_mm=3.0))
    np.testing.assert_allclose(_kernel_widths_mm(unsmoothed), [3.0, 3.0], rtol=0.02)


def test_demons_default_smoothing_is_isotropic_in_mm_on_anisotropic_voxels():
    # Before the fix, the spacing multiplied a pixel width: 1 x 2 mm voxels were smoothed
    # 4 times wider in mm along y than along x, and 2 x 2 mm voxels 4 times wider than 1 mm ones.
    iso = _kernel_widths_mm(
        demons_register(*_impulse_pair((1.0, 1.0), (64, 64)), options=_one_iteration())
    )
    for spacing in ((1.0, 2.0), (2.0, 2.0)):
        widths = _kernel_widths_mm(
            demons_register(*_impulse_pair(spacing, (64, 64)), options=_one_iteration())
        )
        np.testing.assert_allclose(widths, iso, rtol=0.02, err_msg=f"spacing {spacing}")


def test_demons_coarse_levels_use_their_own_voxel_size():
    # smoothing_mm = s: a level shrunk by f smooths by f * s mm (here the last level, f = 2).
    opts = FluidOptions(shrink_factors=(2,), iterations=(1,), smoothing_mm=2.0)
    assert opts.smoothing_per_level() == (4.0,)
    fixed, moving = _impulse_pair((1.0, 1.0), (128, 128))
    field = demons_register(fixed, moving, options=opts)
    assert field.GetSpacing() == (2.0, 2.0)
    # After smoothing and shrinking, only one coarse voxel differs by more than ITK's
    # intensity threshold (0.001), so the field is again the kernel: 4 mm, i.e. 2 voxels of
    # the level (1 mm would be 2 mm; the spacing taken twice, 8 mm).
    np.testing.assert_allclose(_kernel_widths_mm(field), [4.0, 4.0], rtol=0.02)
    explicit = FluidOptions(shrink_factors=(4, 2, 1), iterations=(1, 1, 1), smoothing_mm=(9, 5, 3))
    assert explicit.smoothing_per_level() == (9.0, 5.0, 3.0)


# The same physical registration problem, sampled on different grids: analytic smooth blobs
# (fixed) and the same blobs moved by a smooth known displacement (moving), rendered on each
# grid, so no resampling enters. Demons with smoothing in mm must give about the same field
# in mm on every grid.
_BLOB_RNG = np.random.default_rng(3)
_BLOBS = (
    _BLOB_RNG.uniform(-24, 24, (14, 2)),
    _BLOB_RNG.uniform(3, 7, 14),
    _BLOB_RNG.uniform(0.3, 1.0, 14),
)


def _blobs(spacing, *, moved: bool, extent: float = 64.0) -> sitk.Image:
    size = [int(round(extent / s)) for s in spacing]
    img = sitk.Image(size, sitk.sitkFloat32)
    img.SetSpacing(list(spacing))
    img.SetOrigin([-(n - 1) * s / 2 for n, s in zip(size, spacing, strict=True)])
    y, x = np.meshgrid(
        img.GetOrigin()[1] + spacing[1] * np.arange(size[1]),
        img.GetOrigin()[0] + spacing[0] * np.arange(size[0]),
        indexing="ij",
    )
    if moved:
        x, y = (
            x + 2.0 * np.sin(x / 9.0) * np.cos(y / 11.0),
            y + 1.5 * np.cos(x / 10.0 + 0.3) * np.sin(y / 8.0),
        )
    values = np.zeros_like(x)
    for (cx, cy), w, a in zip(*_BLOBS, strict=True):
        values += a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * w * w))
    out = sitk.GetImageFromArray(values.astype(np.float32))
    out.CopyInformation(img)
    return out


def _field_at(field: sitk.Image, points: np.ndarray) -> np.ndarray:
    t = sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))
    return np.array([np.subtract(t.TransformPoint(tuple(p)), p) for p in points])


def test_demons_gives_the_same_field_in_mm_on_different_samplings():
    points = np.stack(np.meshgrid(np.linspace(-20, 20, 21), np.linspace(-20, 20, 21)), -1)
    points = points.reshape(-1, 2)
    fields = {
        spacing: _field_at(
            demons_register(_blobs(spacing, moved=False), _blobs(spacing, moved=True)), points
        )
        for spacing in ((1.0, 1.0), (2.0, 2.0), (1.0, 2.0), (2.0, 1.0))
    }
    ref = fields[(1.0, 1.0)]
    assert np.linalg.norm(ref, axis=1).mean() > 0.5  # a real displacement (0.72 mm)
    for spacing, f in fields.items():
        diff = np.linalg.norm(f - ref, axis=1)
        # Measured after the fix: mean 0.02-0.04 mm, max 0.05-0.12 mm; before it, the coarser
        # samplings were smoothed 2-4 times wider (mean 0.40-0.62 mm, max 0.83-1.31 mm).
        assert diff.mean() < 0.15 and diff.max() < 0.4, (spacing, diff.mean(), diff.max())


# --------------------------------------------------------------------------------------------
# ANTs (antspyx): run whenever antspyx is importable.


def _textured(size: int = 96, seed: int = 5) -> sitk.Image:
    """Smooth random texture in a soft disc (every region has gradients), centred at 0 mm."""
    rng = np.random.default_rng(seed)
    tex = gaussian_filter(rng.standard_normal((size, size)), 2.0)
    tex = 0.5 + 0.5 * tex / np.abs(tex).max()
    yy, xx = np.mgrid[:size, :size] - (size - 1) / 2
    disc = gaussian_filter(((xx**2 + yy**2) < (0.42 * size) ** 2).astype(float), 1.0)
    img = sitk.GetImageFromArray((disc * tex).astype(np.float32))
    img.SetOrigin(((1 - size) / 2,) * 2)
    return img


def _bump(grid: sitk.Image, amplitude, centre, width: float) -> sitk.Transform:
    """p -> p + amplitude * exp(-|p - centre|^2 / (2 width^2)) (mm)."""
    size, sp, o = grid.GetSize(), grid.GetSpacing(), grid.GetOrigin()
    y, x = np.meshgrid(
        o[1] + sp[1] * np.arange(size[1]), o[0] + sp[0] * np.arange(size[0]), indexing="ij"
    )
    g = np.exp(-((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / (2 * width**2))
    field = sitk.GetImageFromArray(np.stack([amplitude[0] * g, amplitude[1] * g], -1), True)
    field.CopyInformation(grid)
    return sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))


def _known_motion(fixed: sitk.Image, *, affine: bool) -> sitk.Transform:
    """G: moving point -> fixed point; the moving image is ``fixed(G(q))``."""
    bump = _bump(fixed, (4.0, -3.0), (12.0, 6.0), 7.0)
    if not affine:
        return bump
    a = np.deg2rad(8.0)
    pose = sitk.AffineTransform(2)
    pose.SetMatrix(
        tuple((1.05 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])).ravel())
    )
    pose.SetTranslation((12.0, -8.0))
    return sitk.CompositeTransform([bump, pose])  # bump(pose(q))


def _points(image: sitk.Image, threshold: float = 0.1) -> list:
    idx = np.argwhere(sitk.GetArrayFromImage(image) > threshold)[:, ::-1]
    return [image.TransformContinuousIndexToPhysicalPoint(i.astype(float).tolist()) for i in idx]


def _distances(points, first, second) -> np.ndarray:
    """|second(first(p)) - p| for every p (first = None: the identity)."""
    out = []
    for p in points:
        q = first.TransformPoint(p) if first is not None else p
        out.append(np.linalg.norm(np.subtract(second.TransformPoint(q), p)))
    return np.array(out)


@pytest.fixture(scope="module")
def ants_known_motion(tmp_path_factory):
    """antsRegistration SyN (affine + warp) of a moving image made by a known motion."""
    if ants is None:
        pytest.skip("antspyx is not installed (pip install itk-nrreval[ants])")
    tmp = tmp_path_factory.mktemp("ants")
    fixed = _textured()
    motion = _known_motion(fixed, affine=True)
    moving = sitk.Resample(fixed, fixed, motion, sitk.sitkLinear, 0.0)
    sitk.WriteImage(fixed, str(tmp / "fixed.nii.gz"))
    sitk.WriteImage(moving, str(tmp / "moving.nii.gz"))
    out = seeded_ants_registration(
        ants,
        ants.image_read(str(tmp / "fixed.nii.gz")),
        ants.image_read(str(tmp / "moving.nii.gz")),
        seed=1,
        type_of_transform="SyN",
        reg_iterations=(40, 20, 10),
        outprefix=str(tmp / "out_"),
    )
    return fixed, moving, motion, out


@needs_ants
def test_ants_forward_list_maps_fixed_points_to_moving_points(ants_known_motion):
    fixed, _, motion, out = ants_known_motion
    names = [p.rsplit("_", 1)[-1] for p in out["fwdtransforms"]]
    assert names == ["1Warp.nii.gz", "0GenericAffine.mat"]
    forward = chain_transform(out["fwdtransforms"])  # first listed acts first
    # Fixed point p corresponds to the moving point q with G(q) = p: G(forward(p)) = p.
    err = _distances(_points(fixed), forward, motion)
    # Measured (seeds 1-3): mean 0.10-0.11 mm, 95th percentile 0.27-0.28 mm (1 mm voxels, a
    # 12 mm and 8 degree pose plus a 5 mm bump); the other order: p95 2.46 mm.
    assert err.mean() < 0.25 and np.percentile(err, 95) < 0.6, (err.mean(), err.max())
    wrong = _distances(_points(fixed), chain_transform(out["fwdtransforms"][::-1]), motion)
    assert np.percentile(wrong, 95) > 1.5  # the data tell the two orders apart


@needs_ants
def test_ants_inverse_list_maps_moving_points_back(ants_known_motion):
    fixed, moving, motion, out = ants_known_motion
    names = [p.rsplit("_", 1)[-1] for p in out["invtransforms"]]
    assert names == ["0GenericAffine.mat", "1InverseWarp.nii.gz"]
    affine, inverse_warp = (read_transform(p) for p in out["invtransforms"])
    inverse = chain_transform([affine.GetInverse(), inverse_warp])  # whichtoinvert [T, F]
    # Moving point q corresponds to the fixed point G(q).
    q = _points(moving)
    err = np.array(
        [
            np.linalg.norm(np.subtract(inverse.TransformPoint(p), motion.TransformPoint(p)))
            for p in q
        ]
    )
    assert err.mean() < 0.25 and np.percentile(err, 95) < 0.6, (err.mean(), err.max())  # 0.10, 0.26
    # The affine must be inverted: read as listed, the moving points land 25-40 mm off.
    as_listed = chain_transform([affine, inverse_warp])
    off = np.array(
        [
            np.linalg.norm(np.subtract(as_listed.TransformPoint(p), motion.TransformPoint(p)))
            for p in q
        ]
    )
    assert off.mean() > 10
    # And the two lists are each other's inverse (measured: mean 0.002 mm, max 0.04 mm).
    round_trip = _distances(_points(fixed), chain_transform(out["fwdtransforms"]), inverse)
    assert round_trip.mean() < 0.02 and round_trip.max() < 0.2, round_trip.max()


@needs_ants
def test_ants_syn_of_the_fluid_engine_maps_reference_points_to_image_points(tmp_path):
    fixed = _textured()
    motion = _known_motion(fixed, affine=False)
    moving = sitk.Resample(fixed, fixed, motion, sitk.sitkLinear, 0.0)
    forward = ants_syn(ants, fixed, moving, seed=3)
    err = _distances(_points(fixed), forward, motion)
    before = _distances(_points(fixed), None, motion)
    # SyN's defaults do no iterations at full resolution: measured mean 0.11 mm, p95 0.33 mm
    # for a 5 mm bump (mean 0.29 mm, p95 2.1 mm before registration; most points lie away
    # from the bump).
    assert err.mean() < 0.5 * before.mean() and np.percentile(err, 95) < 1.0, (
        err.mean(),
        np.percentile(err, 95),
        before.mean(),
    )


@needs_ants
def test_ants_registration_is_seeded_for_this_call_only(capfd):
    fixed = ants.from_numpy(sitk.GetArrayFromImage(_textured(48)).T.copy())
    saved = getattr(ants.config, "_random_seed", None)
    seeded_ants_registration(ants, fixed, fixed, seed=7, type_of_transform="SyNOnly", verbose=True)
    # antsRegistration's command line: ANTs reads 0 as "from the clock", so seed + 1 is passed.
    assert "--random-seed 8" in capfd.readouterr().out
    assert getattr(ants.config, "_random_seed", None) == saved


@needs_ants
def test_fluid_with_ants_improves_over_affine(population, affine_result, tmp_path):
    images, truths = population
    result = register(
        images, method="fluid", engine="ants", affine=affine_result, seed=2, progress=False
    )
    assert result.engine == "ants"
    ref = result.reference
    assert correspondence_error(result.transforms, ref, truths) < 0.8 * correspondence_error(
        affine_result.transforms, ref, truths
    )
    _check_written(result, tmp_path, images)


def test_demons_smoothing_wider_than_itk_can_do_is_refused():
    fixed, moving = _impulse_pair((1.0, 1.0), (128, 128))
    # ITK itself: from about 26.6 pixels its Gaussian kernel overflows and the field is NaN.
    demons = sitk.DiffeomorphicDemonsRegistrationFilter()
    demons.SetNumberOfIterations(1)
    demons.SetMaximumKernelWidth(200)
    for sigma, nan in ((25.0, False), (27.0, True)):
        demons.SetStandardDeviations(sigma)
        assert np.isnan(sitk.GetArrayFromImage(demons.Execute(fixed, moving))).any() == nan
    fine = [sitk.Image(im) for im in (fixed, moving)]
    for im in fine:
        im.SetSpacing((0.1, 0.1))
    with pytest.raises(InputError, match=r"3 mm is 30\.0 voxels of 0\.1 mm; .* above 25 voxels"):
        demons_register(*fine, options=_one_iteration(smoothing_mm=3.0))


# The step limit. ITK caps a demons update at MaximumUpdateStepLength times the root-mean-square
# voxel size (its normaliser is mean(spacing**2) * L**2), so on anisotropic voxels a "one
# voxel" step exceeded a voxel along the fine axis (2.5 mm on 1.6 x 3.2 mm voxels), which
# tore the field. With the same ramp in both images and a constant intensity offset, one
# iteration gives a uniform update u = 2 s G / (|G|^2 + s^2 / K) (speed s, gradient sum G);
# solving for K gives the cap sqrt(K) in mm.


def _step_limit_mm(spacing, max_step, *, a=0.05, b=0.03, offset=0.2, size=(48, 48)) -> float:
    grid = sitk.Image(list(size), sitk.sitkFloat32)
    grid.SetSpacing(list(spacing))
    y, x = np.meshgrid(
        np.arange(size[1]) * spacing[1], np.arange(size[0]) * spacing[0], indexing="ij"
    )
    ramp = (a * x + b * y).astype(np.float32)
    fixed, moving = sitk.GetImageFromArray(ramp), sitk.GetImageFromArray(ramp + np.float32(offset))
    fixed.CopyInformation(grid)
    moving.CopyInformation(grid)
    # A narrow smoothing keeps the border's different update away from the measured interior.
    options = _one_iteration(max_step=max_step, smoothing_mm=min(spacing))
    field = demons_register(fixed, moving, options=options)
    u = np.linalg.norm(sitk.GetArrayFromImage(field)[10:-10, 10:-10], axis=-1)
    assert u.std() < 1e-3 * u.mean()  # uniform, as the derivation needs
    g = 2 * np.hypot(a, b)  # fixed plus warped moving gradient
    return float(np.sqrt(offset**2 / (2 * offset * g / u.mean() - g**2)))


@pytest.mark.parametrize("spacing", [(1.0, 1.0), (2.0, 2.0), (1.0, 2.0), (1.6, 3.2)])
@pytest.mark.parametrize("max_step", [0.5, 2.0])
def test_demons_step_limit_is_max_step_voxels_of_the_finest_axis(spacing, max_step):
    # Before the fix: 1.58 x max_step mm on 1 x 2 mm voxels, 2.53 x max_step on 1.6 x 3.2.
    assert _step_limit_mm(spacing, max_step) == pytest.approx(max_step * min(spacing), rel=2e-3)


def test_elastix_inputs_are_written_without_nifti_header_noise(tmp_path, capfd):
    # A NIfTI header's fields (descrip, qto_xyz, ...) cannot go into a MetaImage: ITK printed
    # one warning per field and per image on every elastix call.
    from itk_nrreval.experiments.registration._elastix_worker import _write_bare

    img = sitk.GetImageFromArray(np.arange(30, dtype=np.float32).reshape(5, 6))
    img.SetSpacing((0.9, 1.3))
    img.SetOrigin((4.0, -2.0))
    img.SetDirection((0.0, 1.0, -1.0, 0.0))
    sitk.WriteImage(img, str(tmp_path / "a.nii.gz"))
    from_nifti = sitk.ReadImage(str(tmp_path / "a.nii.gz"))
    keys = from_nifti.GetMetaDataKeys()
    assert keys
    capfd.readouterr()
    sitk.WriteImage(from_nifti, str(tmp_path / "noisy.mha"))
    assert "MetaImageIO" in capfd.readouterr().err  # what the plain writer does
    _write_bare(from_nifti, tmp_path / "bare.mha")
    assert "MetaImageIO" not in capfd.readouterr().err
    back = sitk.ReadImage(str(tmp_path / "bare.mha"))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(img))
    np.testing.assert_allclose(back.GetDirection(), img.GetDirection(), atol=1e-6)
    np.testing.assert_allclose(back.GetOrigin(), img.GetOrigin(), atol=1e-6)
    assert from_nifti.GetMetaDataKeys() == keys  # the caller's image is untouched


def _sd_log_jacobian(transform: sitk.Transform, reference: sitk.Image, margin: int = 8) -> float:
    field = sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        reference.GetSize(),
        reference.GetOrigin(),
        reference.GetSpacing(),
        reference.GetDirection(),
    )
    det = sitk.GetArrayFromImage(sitk.DisplacementFieldJacobianDeterminant(field))
    det = det[margin:-margin, margin:-margin]
    return float(np.log(np.clip(det, 1e-3, None)).std())


def test_elastix_bending_weight_regularises_the_bspline(population, affine_result, worker):
    """The bending-energy penalty (elastix's regularisation weight) makes fields smoother;
    weight 0 leaves elastix's map with the similarity metric alone."""
    from itk_nrreval.experiments.registration.bspline import BSplineOptions, elastix_parameters

    plain = elastix_parameters(BSplineOptions(), seed=1)
    assert plain["Metric"] == ["AdvancedMeanSquares"]
    penalised = elastix_parameters(BSplineOptions(bending_weight=0.25), seed=1)
    assert penalised["Metric"] == ["AdvancedMeanSquares", "TransformBendingEnergyPenalty"]
    assert float(penalised["Metric1Weight"][0]) == 0.25
    images, _ = population
    rough = {}
    for weight in (0.0, 5.0):
        res = register(
            images[:3],
            method="pairwise",
            reference=images[0],
            options={"bending_weight": weight, "grid_spacing": 8.0},
            elastix_worker=worker,
            progress=False,
        )
        rough[weight] = np.mean([_sd_log_jacobian(t, images[0]) for t in res.transforms[1:]])
    assert rough[5.0] < 0.8 * rough[0.0], rough
