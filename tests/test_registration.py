"""nrreval register: real engines on a small 2D population with known correspondence.

The population is a smooth brain-like phantom warped by known transforms (random affine and
a smooth displacement of up to 4 mm), so the true correspondence error of any registration
can be measured: for each reference point p, the template points ``S_i(R_i(p))`` of all
images should coincide (``S_i`` maps image i's points to the template, ``R_i`` is the
registration's reference -> image transform).
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.ndimage import gaussian_filter

from itk_nrreval import InputError, RegistrationResult, register
from itk_nrreval.cli import main
from itk_nrreval.manifest import load_manifest
from itk_nrreval.registration import EngineError
from itk_nrreval.registration._elastix_worker import ElastixWorker

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
def worker():
    with ElastixWorker() as w:
        yield w


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


def test_missing_ants_is_a_clear_input_error(population):
    try:
        import ants  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("antspyx is installed")
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


def test_cli_missing_engine_is_one_line_exit_2(population, tmp_path, capsys):
    try:
        import ants  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("antspyx is installed")
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
