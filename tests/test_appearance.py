"""Full appearance-model diagnostics (paper, Table 1): model, synthesis, cells, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.ndimage import gaussian_filter
from scipy.spatial.distance import cdist

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.experiments.appearance.model import (
    AppearanceModel,
    affine_part,
    appearance_diagnostics,
    fit_appearance,
    nearest_images,
)
from itk_nrreval.io._images import Geometry

N_IMAGES = 7
SIZE = 48
SPACING = (1.5, 1.25)  # ITK (x, y)
ORIGIN = (-20.0, 10.0)


def _image(array: np.ndarray) -> sitk.Image:
    img = sitk.GetImageFromArray(array.astype(np.float32))
    img.SetSpacing(SPACING)
    img.SetOrigin(ORIGIN)
    return img


def _smooth(rng, sigma, scale, shape=(SIZE, SIZE)):
    return gaussian_filter(rng.normal(size=shape), sigma) * scale


def _affine(rng) -> sitk.AffineTransform:
    a = sitk.AffineTransform(2)
    a.SetMatrix(tuple((np.eye(2) + rng.normal(scale=0.03, size=(2, 2))).ravel()))
    a.SetTranslation(tuple(rng.normal(scale=1.5, size=2)))
    a.SetCenter((ORIGIN[0] + 35.0, ORIGIN[1] + 30.0))
    return a


def _field(rng) -> sitk.DisplacementFieldTransform:
    u = np.stack([_smooth(rng, 6.0, 25.0) for _ in range(2)], axis=-1)  # a few mm
    return _field_from(u)


def _field_from(u: np.ndarray) -> sitk.DisplacementFieldTransform:
    img = sitk.GetImageFromArray(u, isVector=True)
    img.SetSpacing(SPACING)
    img.SetOrigin(ORIGIN)
    return nr.io.transforms.field_transform(img)


def _write_case(folder, *, warped: bool, seed: int):
    """N images (smooth structure + intensity changes) and one registration on disk."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    base = _smooth(rng, 3.0, 40.0) + 5.0
    images, transforms = [], []
    for i in range(N_IMAGES):
        arr = base * (1 + 0.1 * rng.normal()) + _smooth(rng, 2.0, 10.0)
        path = folder / f"s{i}.mha"
        sitk.WriteImage(_image(arr), str(path))
        images.append(str(path))
        if warped:
            t = sitk.CompositeTransform([_affine(rng), _field(rng)])  # affine(warp(p))
        else:
            t = sitk.AffineTransform(2)  # identity: no shape variation at all
        tpath = folder / f"t{i}.h5"
        sitk.WriteTransform(t, str(tpath))
        transforms.append(str(tpath))
    reference = folder / "ref.mha"
    sitk.WriteImage(_image(base), str(reference))
    manifest = {
        "images": images,
        "registrations": {"reg": {"reference": str(reference), "transforms": transforms}},
    }
    path = folder / "manifest.yaml"
    nr.write_manifest(manifest, path)
    return path


@pytest.fixture(scope="module")
def identity_case(tmp_path_factory):
    return _write_case(tmp_path_factory.mktemp("identity"), warped=False, seed=1)


@pytest.fixture(scope="module")
def warped_case(tmp_path_factory):
    return _write_case(tmp_path_factory.mktemp("warped"), warped=True, seed=2)


@pytest.fixture(scope="module")
def warped_result(warped_case):
    return appearance_diagnostics(
        warped_case, registration="reg", n_samples=60, seed=5, progress=False
    )


# ----------------------------------------------------------------------------- the model


def test_identity_shape_projection_equals_raw(identity_case):
    r = appearance_diagnostics(identity_case, registration="reg", n_samples=150, progress=False)
    assert r.n_shape_modes == 0
    assert r.n_texture_modes == N_IMAGES - 1 == r.n_modes
    np.testing.assert_allclose(r.representation_error, 0.0, atol=1e-9)
    np.testing.assert_array_equal(r.raw.counts, r.projected.counts)
    assert r.raw.counts.sum() == r.projected.counts.sum() == 150
    assert r.raw.specificity == pytest.approx(r.projected.specificity, rel=1e-12)
    assert r.reassigned_fraction == 0.0
    assert r.raw.stderr == pytest.approx(r.projected.stderr, rel=1e-9)


def test_training_params_reproduce_shapes_and_textures(rng):
    g = Geometry((9, 7), (1.0, 2.0), (0.0, 0.0), (1.0, 0.0, 0.0, 1.0))
    u = rng.normal(size=(6, 7, 9, 2))
    tex = rng.normal(size=(6, 7, 9)) * 30
    model = AppearanceModel.from_fields(u, tex, geometry=g)
    assert (model.n_shape_modes, model.n_texture_modes, model.n_modes) == (5, 5, 5)
    for i in range(6):
        ui, gi = model.instance(model.training_params[i])
        np.testing.assert_allclose(ui, u[i], atol=1e-9)
        np.testing.assert_allclose(gi, tex[i], atol=1e-9)
    # W equalizes total shape and texture variance
    var_s = np.sum((u - u.mean(0)) ** 2)
    var_g = np.sum((tex - tex.mean(0)) ** 2)
    assert model.shape_weight == pytest.approx(np.sqrt(var_g / var_s))
    # combined parameters: centred, decorrelated, variances as stated
    c = model.training_params
    np.testing.assert_allclose(c.mean(0), 0.0, atol=1e-9)
    np.testing.assert_allclose(c.T @ c / 5, np.diag(model.combined_variances), atol=1e-8)


def test_model_rejects_no_variation():
    g = Geometry((4, 3), (1.0, 1.0), (0.0, 0.0), (1.0, 0.0, 0.0, 1.0))
    with pytest.raises(nr.InputError, match="all shapes and textures are identical"):
        AppearanceModel.from_fields(np.zeros((4, 3, 4, 2)), np.ones((4, 3, 4)), geometry=g)
    with pytest.raises(nr.InputError, match="at least 3 images"):
        AppearanceModel.from_fields(np.zeros((2, 3, 4, 2)), np.ones((2, 3, 4)), geometry=g)


def test_sample_params_do_not_depend_on_chunks(rng):
    g = Geometry((5, 4), (1.0, 1.0), (0.0, 0.0), (1.0, 0.0, 0.0, 1.0))
    model = AppearanceModel.from_fields(
        rng.normal(size=(5, 4, 5, 2)), rng.normal(size=(5, 4, 5)), geometry=g
    )
    whole = model.sample_params(3, 0, 20)
    parts = np.vstack([model.sample_params(3, 0, 7), model.sample_params(3, 7, 20)])
    np.testing.assert_array_equal(whole, parts)


def test_affine_part_kept_or_fitted(rng):
    grid = Geometry((20, 16), SPACING, ORIGIN, (1.0, 0.0, 0.0, 1.0))
    a = _affine(rng)
    points = [(ORIGIN[0] + x, ORIGIN[1] + y) for x in (0.0, 13.0, 29.0) for y in (2.0, 17.0)]
    # a chain with a warp: the affine is kept exactly, the warp left out
    chained = sitk.CompositeTransform([a, _field_from(np.ones((16, 20, 2)) * 3.0)])
    # a dense field with the affine folded in: the least-squares fit recovers it
    dense = nr.io.transforms.field_transform(nr.io.transforms.displacement_field(a, grid))
    for t in (a, chained, dense):
        got = affine_part(t, grid)
        for p in points:
            np.testing.assert_allclose(got.TransformPoint(p), a.TransformPoint(p), atol=1e-6)


# ----------------------------------------------------------------------------- the cells


def test_nearest_images_matches_cdist(rng):
    train = rng.normal(size=(9, 300))
    samples = rng.normal(size=(40, 300))
    dist, index = nearest_images(samples, train)
    d = cdist(samples, train)
    np.testing.assert_array_equal(index, d.argmin(axis=1))
    np.testing.assert_allclose(dist, d.min(axis=1), rtol=1e-12)


def test_cells_match_brute_force(warped_case, warped_result):
    r = warped_result
    model, raw = fit_appearance(warped_case, registration="reg", progress=False)
    assert model.n_shape_modes == model.n_texture_modes == N_IMAGES - 1
    samples = np.stack([model.synthesise(c) for c in model.sample_params(5, 0, 60)])
    samples = samples.reshape(60, -1)
    raw = raw.reshape(N_IMAGES, -1)
    projected = np.stack([model.synthesise(c) for c in model.training_params])
    projected = projected.reshape(N_IMAGES, -1)
    np.testing.assert_allclose(
        r.representation_error, np.linalg.norm(raw - projected, axis=1), rtol=1e-9
    )
    assert r.representation_error.max() > 0  # warping loses something
    nearest_index = {}
    for variant, train in (("raw", raw), ("projected", projected)):
        cells = getattr(r, variant)
        d = cdist(samples, train)
        nearest_index[variant] = d.argmin(axis=1)
        nearest = d.min(axis=1)
        np.testing.assert_array_equal(
            cells.counts, np.bincount(d.argmin(axis=1), minlength=N_IMAGES)
        )
        assert cells.specificity == pytest.approx(nearest.mean(), rel=1e-10)
        assert cells.stderr == pytest.approx(nearest.std() / np.sqrt(59), rel=1e-8)
    changed = nearest_index["raw"] != nearest_index["projected"]
    assert r.reassigned_fraction == pytest.approx(changed.mean())
    d_train = cdist(raw, raw) + np.diag(np.full(N_IMAGES, np.inf))
    np.testing.assert_allclose(r.training_spacing, d_train.min(axis=1), rtol=1e-8)


def test_counts_sum_and_same_seed_same_table(warped_case, warped_result):
    r = warped_result
    assert r.raw.counts.sum() == r.projected.counts.sum() == 60
    again = appearance_diagnostics(
        warped_case, registration="reg", n_samples=60, seed=5, progress=False
    )
    assert json.dumps(again.to_dict()) == json.dumps(r.to_dict())
    assert 0.0 <= r.raw.empty_fraction <= r.raw.near_empty_fraction <= 1.0
    assert r.raw.near_empty_threshold == pytest.approx(0.1 * 60 / N_IMAGES)


def test_python_api_errors(warped_case):
    with pytest.raises(nr.InputError, match="registration 'nope' is not in the manifest"):
        appearance_diagnostics(warped_case, registration="nope", progress=False)
    with pytest.raises(ValueError, match="n_samples must be an integer"):
        appearance_diagnostics(warped_case, registration="reg", n_samples=1, progress=False)
    with pytest.raises(ValueError, match="seed must be an integer"):
        appearance_diagnostics(warped_case, registration="reg", seed=-1, progress=False)


# ----------------------------------------------------------------------------- the CLI


def test_cli_writes_table_figure_json(identity_case, tmp_path, capsys):
    out = tmp_path / "diag"
    args = ["diagnose", str(identity_case), "--registration", "reg", "--samples", "30"]
    assert main([*args, "--seed", "2", "--out", str(out), "--no-progress"]) == 0
    md = (out / "appearance_table1.md").read_text()
    assert "| Image | 1 | 2 |" in md and "*projected*" in md
    rows = (out / "appearance_table1.csv").read_text().splitlines()
    assert rows[0].startswith("registration,variant,image_1,")
    assert [r.split(",")[1] for r in rows[1:]] == ["raw", "projected"]
    assert sum(int(v) for v in rows[1].split(",")[2 : 2 + N_IMAGES]) == 30
    data = json.loads((out / "appearance_diagnostics.json").read_text())
    assert (
        data["registrations"][0]["raw"]["counts"] == data["registrations"][0]["projected"]["counts"]
    )
    assert (out / "appearance_cells.png").read_bytes()[:4] == b"\x89PNG"
    assert "results written to" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--registration", "nope"], "--registration nope: not in"),
        (["--registration", "reg", "--samples", "1"], "--samples: expected an integer >= 2"),
        (["--registration", "reg", "--samples", "many"], "--samples: expected an integer >= 2"),
        (["--registration", "reg", "--seed", "-3"], "--seed: expected an integer in [0, "),
    ],
)
def test_cli_bad_options_one_line(identity_case, tmp_path, capsys, extra, message):
    code = main(["diagnose", str(identity_case), *extra, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and message in err
    assert not (tmp_path / "o").exists()


def test_cli_bad_manifest_and_out(identity_case, tmp_path, capsys):
    code = main(
        [
            "diagnose",
            str(tmp_path / "missing.yaml"),
            "--registration",
            "r",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "manifest file not found" in err
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code = main(["diagnose", str(identity_case), "--registration", "reg", "--out", str(blocker)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "exists and is not a folder" in err


@pytest.mark.parametrize("dim", [2, 3])
def test_synthesise_warps_texture_by_the_shape(rng, dim):
    shape = (10, 12, 14)[-dim:]  # numpy order
    g = Geometry(shape[::-1], (2.0,) * dim, (0.0,) * dim, tuple(np.eye(dim).ravel()))
    along_x, along_y = np.eye(dim)[0] * 2.0, np.eye(dim)[1]  # mm, ITK (x, y[, z]) components
    u = np.stack(
        [np.zeros((*shape, dim)), *(np.broadcast_to(v, (*shape, dim)) for v in (along_x, along_y))]
    )
    tex = rng.normal(size=(3, *shape))
    model = AppearanceModel.from_fields(u, tex, geometry=g)
    img = model.synthesise(model.training_params[1])
    # image(q) = texture(phi^-1(q)) = texture(q - 2 mm x): one voxel back along x (last axis)
    inner = (slice(3, -3),) * dim
    np.testing.assert_allclose(img[inner], np.roll(tex[1], 1, axis=-1)[inner], atol=1e-3)
    np.testing.assert_allclose(model.synthesise(model.training_params[0]), tex[0], atol=1e-9)
