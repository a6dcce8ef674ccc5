"""register_multimodal: a group of T1 and T2 images, registered jointly or per modality.

A tiny two-contrast population (3 subjects, each imaged T1- and T2-like, the same anatomy and
true transform for both images of a subject) on a coarse 2D grid, real engines (SimpleITK
affine, elastix B-spline). The true correspondence error of a registration is measured as in
test_registration: every image's template points ``S_i(T_i(p))`` over the reference's head
should coincide.
"""

from __future__ import annotations

import dataclasses
import json
import re
import warnings

import numpy as np
import pytest
import SimpleITK as sitk

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval import InputError
from itk_nrreval._output import MARKER
from itk_nrreval.cli import main
from itk_nrreval.experiments.correspondence import correspondence_error
from itk_nrreval.experiments.registration import (
    MultimodalResult,
    RegistrationResult,
    register_multimodal,
)
from itk_nrreval.experiments.registration.affine import AffineOptions, affine_register
from itk_nrreval.experiments.registration.bspline import BSplineOptions, sitk_bspline
from itk_nrreval.io.manifest import load_manifest, write_manifest
from itk_nrreval.io.transforms import displacement_field

N_SUBJECTS = 3
CONTRASTS = ("t1", "t2")
GROUPS = [c for c in CONTRASTS for _ in range(N_SUBJECTS)]


@pytest.fixture(scope="module")
def population():
    return make_population(
        "phantom", dim=2, n=N_SUBJECTS, seed=0, spacing=3.2, size=72, contrasts=CONTRASTS
    )


@pytest.fixture(scope="module")
def images(population):
    return [s.images[c] for c in CONTRASTS for s in population.subjects]


@pytest.fixture(scope="module")
def truth(population):
    """Per image, the true transform image point -> template point."""
    return [s.subject_to_template for _ in CONTRASTS for s in population.subjects]


@pytest.fixture(scope="module")
def worker(elastix_worker):
    return elastix_worker  # the session's (conftest.py): itk-elastix loaded once


@pytest.fixture(scope="module")
def results(images, worker):
    """Both strategies, and the affine stage of the joint one (the control)."""
    runs = {
        "joint": {"strategy": "joint"},
        "per-group": {"strategy": "per-group"},
        "affine": {"strategy": "joint", "deformable": False},
    }
    return {
        name: register_multimodal(
            images, GROUPS, **kw, seed=3, progress=False, elastix_worker=worker
        )
        for name, kw in runs.items()
    }


def _error(transforms, result: RegistrationResult, population, truth) -> float:
    """Mean distance (mm) of each image's template point from the group mean, over the head."""
    ref = result.reference
    head = sitk.Resample(
        population.template_labels,
        ref,
        truth[result.reference_index],  # reference points -> template points
        sitk.sitkNearestNeighbor,
    )
    mask = sitk.GetArrayFromImage(head) > 0
    points = []
    for t, s in zip(transforms, truth, strict=True):
        field = sitk.TransformToDisplacementField(
            sitk.CompositeTransform([s, t]),  # s(t(p))
            sitk.sitkVectorFloat64,
            ref.GetSize(),
            ref.GetOrigin(),
            ref.GetSpacing(),
            ref.GetDirection(),
        )
        points.append(sitk.GetArrayFromImage(field)[mask])
    y = np.stack(points)
    return float(np.linalg.norm(y - y.mean(axis=0), axis=-1).mean())


def test_both_strategies_map_reference_points_to_image_points(results, population, truth):
    affine = results["affine"]
    identity = [sitk.Transform(2, sitk.sitkIdentity)] * len(truth)
    before = _error(identity, affine, population, truth)
    after_affine = _error(affine.transforms, affine, population, truth)
    assert after_affine < 0.7 * before
    for name in ("joint", "per-group"):
        r = results[name]
        assert r.reference_index == affine.reference_index  # the same T1 near-mean image
        err = _error(r.transforms, r, population, truth)
        assert err < 0.6 * after_affine, f"{name}: {err:.2f} mm vs affine {after_affine:.2f} mm"
        assert err < 2.5, name


# --------------------------------------------------------------------------------------------
# Composition order against known motions. The engines are replaced by an oracle that returns
# the true transforms (reference point -> template -> image point, from the population's
# known subject <-> template maps), and the references are fixed to two different subjects so
# that the true link between them is far from the identity. Whatever register_multimodal does
# with the oracle's transforms is then checked against the truth alone: composed right, every
# T2 image lands in the T1 reference frame (error ~ the accuracy of the synthetic inverse
# maps); with the link omitted, reversed in order or inverted, it does not.

T1_REF, T2_REF = 0, 2  # subjects of the two group references (different anatomy and pose)


@pytest.fixture(scope="module")
def inverse_truth(population):
    """Per image, the true transform template point -> image point (inverse of `truth`)."""
    return [s.template_to_subject for _ in CONTRASTS for s in population.subjects]


def _true(truth, inverse_truth, reference: int, image: int) -> sitk.Transform:
    """Image `reference`'s points -> image `image`'s points: ``S_image^-1 o S_reference``."""
    return sitk.CompositeTransform([inverse_truth[image], truth[reference]])


@pytest.fixture(scope="module")
def oracle_result(images, truth, inverse_truth):
    import itk_nrreval.experiments.registration.multimodal as mm

    chosen = {"t1": T1_REF, "t2": T2_REF}
    arrays = [sitk.GetArrayFromImage(im) for im in images]

    def choose(group_images, choice, **_):
        first = sitk.GetArrayFromImage(group_images[0])
        g = GROUPS[next(i for i, a in enumerate(arrays) if np.array_equal(a, first))]
        return chosen[g], [None] * len(group_images), None

    def stage(self, indices, reference, *args, **kwargs):
        return [_true(truth, inverse_truth, reference, i) for i in indices]

    def link(self, reference, other, *args, **kwargs):
        return _true(truth, inverse_truth, reference, other)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(mm, "choose_reference", choose)
        mp.setattr(mm._Run, "stage", stage)
        mp.setattr(mm._Run, "link", link)
        result = register_multimodal(
            images, GROUPS, strategy="per-group", engine="simpleitk", progress=False
        )
    return result


def test_per_group_composition_brings_t2_into_the_t1_frame(
    oracle_result, population, truth, inverse_truth
):
    r = oracle_result
    r0, rg = T1_REF, N_SUBJECTS + T2_REF
    assert r.reference_index == r0 and r.group_references == {"t1": r0, "t2": rg}
    t2 = [i for i, g in enumerate(GROUPS) if g == "t2"]
    within = {j: _true(truth, inverse_truth, rg, j) for j in t2}  # T_j: T2 reference -> image j
    link = r.links["t2"]  # L: T1 reference -> T2 reference
    inverse_link = _true(truth, inverse_truth, rg, r0)  # L^-1 (exact, from the truth)
    variants = {
        "composed": list(r.transforms),
        "link omitted": [within.get(i, t) for i, t in enumerate(r.transforms)],
        "order reversed": [
            sitk.CompositeTransform([link, within[i]]) if i in within else t
            for i, t in enumerate(r.transforms)
        ],
        "link inverted": [
            sitk.CompositeTransform([within[i], inverse_link]) if i in within else t
            for i, t in enumerate(r.transforms)
        ],
    }
    error = {k: _error(v, r, population, truth) for k, v in variants.items()}
    # How far apart the two references' anatomies are: the scale of a wrong link's error.
    identity = sitk.Transform(2, sitk.sitkIdentity)
    gap = _error([identity, identity], r, population, [truth[r0], truth[rg]])
    assert gap > 2.0, f"the test needs references far apart, got {gap:.2f} mm"
    assert error["composed"] < 0.1, error
    for name in ("link omitted", "order reversed", "link inverted"):
        assert error[name] > 20 * error["composed"] and error[name] > 0.5, (name, error)
    # The T1 images are untouched by the link: each is its own true transform.
    for i in (i for i, g in enumerate(GROUPS) if g == "t1"):
        p = r.reference.TransformIndexToPhysicalPoint((30, 41))
        np.testing.assert_allclose(
            r.transforms[i].TransformPoint(p),
            _true(truth, inverse_truth, r0, i).TransformPoint(p),
            atol=1e-9,
        )


def test_the_link_maps_t1_reference_points_to_t2_reference_points(
    results, population, truth, inverse_truth
):
    """Real engines: the per-group link is near the true link, far from the identity."""
    r = results["per-group"]
    r0, rg = r.reference_index, r.group_references["t2"]
    ref = r.reference
    head = sitk.Resample(population.template_labels, ref, truth[r0], sitk.sitkNearestNeighbor)
    mask = sitk.GetArrayFromImage(head) > 0

    def points(t):
        return sitk.GetArrayFromImage(displacement_field(t, ref))[mask]

    true_link = points(_true(truth, inverse_truth, r0, rg))
    error = np.linalg.norm(points(r.links["t2"]) - true_link, axis=-1).mean()
    if r0 % N_SUBJECTS == rg % N_SUBJECTS:  # the same subject: the true link is the identity
        assert error < 1.0
    else:
        off = np.linalg.norm(points(sitk.Transform(2, sitk.sitkIdentity)) - true_link, axis=-1)
        assert error < 0.5 * off.mean(), (error, off.mean())


def test_the_results_say_what_they_are(results, images):
    joint, per_group = results["joint"], results["per-group"]
    for r in (joint, per_group):
        assert isinstance(r, MultimodalResult) and r.method == "multimodal"
        assert r.groups == tuple(GROUPS) and r.reference_group == "t1"
        assert GROUPS[r.reference_index] == "t1"
        np.testing.assert_array_equal(
            sitk.GetArrayFromImage(r.reference), sitk.GetArrayFromImage(images[r.reference_index])
        )
        json.dumps(r.settings)
        # the reference image itself is not moved
        p = r.reference.TransformIndexToPhysicalPoint((20, 30))
        np.testing.assert_allclose(r.transforms[r.reference_index].TransformPoint(p), p)
    assert joint.strategy == "joint" and joint.links == {}
    assert set(joint.group_references) == {"t1"}
    assert per_group.strategy == "per-group" and set(per_group.links) == {"t2"}
    r_t2 = per_group.group_references["t2"]
    assert GROUPS[r_t2] == "t2"
    # The T2 reference's own transform is the link: T1 reference points -> its points.
    link = per_group.links["t2"]
    grid = per_group.reference
    for index in [(10, 12), (36, 36), (50, 20)]:
        p = grid.TransformIndexToPhysicalPoint(index)
        np.testing.assert_allclose(
            per_group.transforms[r_t2].TransformPoint(p), link.TransformPoint(p), atol=1e-9
        )


def test_the_link_is_shared_by_every_image_of_the_other_group(results, population, truth):
    """Per group, per-group's T2 images agree with each other at least as well as joint's."""
    joint, per_group = results["joint"], results["per-group"]
    t2 = [i for i, g in enumerate(GROUPS) if g == "t2"]

    def spread(r):
        return _error([r.transforms[i] for i in t2], r, population, [truth[i] for i in t2])

    assert spread(per_group) < 2.0
    assert spread(joint) < 2.5


def test_the_manifest_written_loads_and_evaluates_with_groups(results, population, truth, tmp_path):
    manifest = write_population(population, tmp_path / "pop", montage=False, progress=False)
    m = load_manifest(manifest)
    names = [p.name.removesuffix(".nii.gz") for p in m.images]
    for name, r in results.items():
        r.add_to_manifest(manifest, name, out=tmp_path / name, names=names)
    m = load_manifest(manifest)
    assert m.groups == tuple(GROUPS)
    assert list(m.registrations) == ["truth", "joint", "per-group", "affine"]
    reg = m.registrations["per-group"]
    assert reg.reference_index == results["per-group"].reference_index
    assert reg.parameters["strategy"] == "per-group"
    assert reg.parameters["links"] == {"t2": "link_t2.h5"}
    log = json.loads((tmp_path / "per-group" / "registration.json").read_text())
    assert log["links"] == {"t2": "link_t2.h5"} and log["groups"] == GROUPS
    link = sitk.ReadTransform(str(tmp_path / "per-group" / "link_t2.h5"))
    p = (3.0, -7.0)
    np.testing.assert_allclose(
        link.TransformPoint(p), results["per-group"].links["t2"].TransformPoint(p), atol=1e-9
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        evaluation = nr.evaluate(manifest, n_samples=2000, confidence=False, progress=False)
    for name in m.registrations:
        mix = evaluation.scores[name].specificity.mixture
        assert mix is not None and tuple(mix.groups) == ("t1", "t2"), name
        assert int(mix.nearest_counts.sum()) == 2000
    head = sitk.GetArrayFromImage(population.template_labels) > 0
    error = correspondence_error(evaluation, manifest, truth, mask=head)
    assert error["truth"] < 0.1
    assert error["joint"] < 0.6 * error["affine"]
    assert error["per-group"] < 0.6 * error["affine"]


def test_a_manifest_with_other_groups_is_refused(results, population, tmp_path):
    manifest = write_population(population, tmp_path / "pop", montage=False, progress=False)
    other = dataclasses.replace(results["affine"], groups=("a", "b") * N_SUBJECTS)
    with pytest.raises(InputError, match="groups"):
        other.add_to_manifest(manifest, "other", out=tmp_path / "other")


def test_the_same_seed_gives_the_same_transforms(images):
    runs = [
        register_multimodal(
            images, GROUPS, strategy="per-group", deformable=False, seed=0, progress=False
        )
        for _ in range(2)
    ]
    for a, b in zip(runs[0].transforms, runs[1].transforms, strict=True):
        np.testing.assert_array_equal(a.GetParameters(), b.GetParameters())
    assert runs[0].engine == "simpleitk"  # no B-spline stage: no elastix


def test_out_writes_the_result_links_and_settings(images, tmp_path):
    """``register_multimodal(out=...)`` writes the transforms, reference and links;
    registration.json holds the settings (in this order: the file's layout)."""
    out = tmp_path / "per-group"
    result = register_multimodal(
        images,
        GROUPS,
        strategy="per-group",
        deformable=False,
        affine_options={"iterations": 50},
        seed=4,
        out=out,
        progress=False,
    )
    t1, t2 = result.group_references["t1"], result.group_references["t2"]
    assert result.reference_index == t1 and GROUPS[t1] == "t1" and GROUPS[t2] == "t2"
    affine = {k: v for k, v in dataclasses.asdict(AffineOptions()).items() if k != "metric"}
    pairwise = {k: v for k, v in dataclasses.asdict(BSplineOptions()).items() if k != "metric"}
    settings = {
        "method": "multimodal",
        "strategy": "per-group",
        "engine": "elastix",
        "seed": 4,
        "n_images": len(images),
        "images": None,
        "groups": GROUPS,
        "reference_group": "t1",
        "reference_choice": "near-mean of the reference group",
        "group_references": {"t1": t1, "t2": t2},
        "metric": "correlation",
        "cross_metric": "mattes",
        "deformable": False,
        "affine_options": {**affine, "sampling": 1.0, "iterations": 50},
        "options": pairwise,
    }
    assert list(result.settings.items()) == list(settings.items())
    assert result.engine == "simpleitk"  # no B-spline stage
    transforms = [f"{i:03d}_image{i:03d}.h5" for i in range(len(images))]
    assert sorted(p.name for p in out.iterdir() if p.name != MARKER) == sorted(
        ["reference.nii.gz", "registration.json", "link_t2.h5", *transforms]
    )
    log = json.loads((out / "registration.json").read_text())
    after = ["reference_index", "seconds", "reference", "transforms", "convention", "links"]
    assert list(log) == [*settings, *after]
    assert {k: log[k] for k in settings} == json.loads(json.dumps(settings))
    assert log["links"] == {"t2": "link_t2.h5"} and log["transforms"] == transforms
    link = sitk.ReadTransform(str(out / "link_t2.h5"))
    p = result.reference.TransformIndexToPhysicalPoint((30, 41))
    np.testing.assert_allclose(link.TransformPoint(p), result.links["t2"].TransformPoint(p))


def test_simpleitk_bspline_with_mutual_information_aligns_t2_to_t1(population, truth):
    """The SimpleITK engine's metric option: Mattes MI across contrasts improves on affine."""
    ref, moving = population.subjects[0].images["t1"], population.subjects[1].images["t2"]
    a = affine_register(ref, moving, options=AffineOptions(metric="mattes", sampling=1.0), seed=1)
    b = sitk_bspline(
        ref,
        moving,
        initial=a,
        grid_spacing=16.0,
        levels=2,
        iterations=60,
        sampling=1.0,
        seed=1,
        metric="mattes",
    )
    pair = [truth[0], truth[N_SUBJECTS + 1]]
    result = RegistrationResult("affine", "simpleitk", (a,), ref, 0, ())
    ident = sitk.Transform(2, sitk.sitkIdentity)
    before = _error([ident, a], result, population, pair)
    after = _error([ident, sitk.CompositeTransform([a, b])], result, population, pair)
    assert after < 0.8 * before


@pytest.mark.parametrize(
    ("groups", "kwargs", "message"),
    [
        (GROUPS[:-1], {}, "5 labels for 6 images"),
        (["t1"] * 5 + ["t2"], {}, "group 't2' has 1 image"),
        (["t1", "t1", "t1", "t2", "t2", None], {}, "strings or integers"),
        ("t1t1t1t2t2t2", {}, "one group label per image"),
        (GROUPS, {"strategy": "both"}, "strategy"),
        (GROUPS, {"engine": "ants"}, "engine"),
        (GROUPS, {"reference_group": "flair"}, "reference_group"),
        (GROUPS, {"options": {"metric": "mattes"}}, "cross_metric"),
        (GROUPS, {"metric": "entropy"}, "metric"),
        (GROUPS, {"options": {"grid_size": 3}}, "unknown 'grid_size'"),
        (
            GROUPS,
            {"engine": "simpleitk", "options": {"bending_weight": 1.0}},
            "bending_weight needs the elastix engine, not 'simpleitk'",
        ),
    ],
)
def test_bad_arguments_are_one_line_input_errors(images, groups, kwargs, message):
    with pytest.raises(InputError, match=message) as err:
        register_multimodal(images, groups, **kwargs, progress=False)
    assert "\n" not in str(err.value)


# --------------------------------------------------------------------------------------------
# The command line: `nrreval register --method multimodal`.


@pytest.fixture(scope="module")
def written(population, tmp_path_factory):
    """The population on disk: its manifest (images, groups, truth) and image paths."""
    manifest = write_population(
        population, tmp_path_factory.mktemp("cli") / "pop", montage=False, progress=False
    )
    return manifest, [str(p) for p in load_manifest(manifest).images]


def test_cli_registers_with_the_manifest_groups(
    written, results, population, truth, worker, capsys, monkeypatch
):
    import itk_nrreval.experiments.registration.multimodal as mm

    # The command's elastix jobs go to the running worker rather than to one it starts:
    # loading itk-elastix in a new worker is about 10 s of CPU, and starting and stopping
    # a worker when none is given is elastix_worker_for's, checked in test_registration
    # (test_a_worker_is_started_for_the_block_only_when_none_is_given).
    own = mm.elastix_worker_for
    monkeypatch.setattr(mm, "elastix_worker_for", lambda given, **kw: own(given or worker, **kw))
    manifest, paths = written
    out = manifest.parent / "per-group"
    code = main(
        [
            "register",
            "--images",
            *paths,
            "--method",
            "multimodal",
            "--strategy",
            "per-group",
            "--out",
            str(out),
            "--seed",
            "3",
            "--no-progress",
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert "multimodal per-group" in capsys.readouterr().out
    m = load_manifest(manifest)
    assert m.groups == tuple(GROUPS)  # read from the manifest, left as it was
    reg = m.registrations["multimodal-per-group"]
    assert reg.parameters["strategy"] == "per-group" and reg.parameters["method"] == "multimodal"
    assert GROUPS[reg.reference_index] == "t1"
    assert (out / "link_t2.h5").is_file()
    transforms = [sitk.ReadTransform(str(chain[0])) for chain in reg.transforms]
    result = RegistrationResult(
        "multimodal",
        "elastix",
        tuple(transforms),
        sitk.ReadImage(str(reg.reference)),
        reg.reference_index,
        (),
    )
    affine = results["affine"]
    after_affine = _error(affine.transforms, affine, population, truth)
    assert _error(transforms, result, population, truth) < 0.6 * after_affine


def _without_groups(manifest, folder):
    m = load_manifest(manifest)
    path = folder / "manifest_no_groups.yaml"
    write_manifest(dataclasses.replace(m, groups=None), path)
    return path


@pytest.mark.parametrize(
    ("args", "manifest", "message"),
    [
        ([], "missing", "needs each image's group: give --groups .* does not exist"),
        ([], "no groups", "needs each image's group: give --groups .* has none"),
        (["--groups", *GROUPS[:-1]], "missing", "groups: 5 labels for 6 images"),
        (["--groups", *(["a"] * 5), "b"], "missing", "group 'b' has 1 image"),
        (["--groups", *(["a", "b"] * N_SUBJECTS)], "with groups", "--groups differ from"),
        (["--reference-choice", "near-mean"], "with groups", "chooses its references"),
        (["--engine", "ants"], "with groups", "engine: 'ants' is not one of"),
        (["--strategy", "both"], "with groups", "invalid choice: 'both'"),
    ],
)
def test_cli_bad_multimodal_input_is_one_line_exit_2(
    written, tmp_path, capsys, args, manifest, message
):
    path, paths = written
    chosen = {
        "missing": tmp_path / "missing.yaml",
        "no groups": _without_groups(path, path.parent),
        "with groups": path,
    }[manifest]
    out = tmp_path / "out"
    code = main(
        [
            "register",
            "--images",
            *paths,
            "--method",
            "multimodal",
            *args,
            "--out",
            str(out),
            "--manifest",
            str(chosen),
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err
    assert code == 2, err
    assert re.search(message, err), err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()  # refused before any registration


def test_cli_multimodal_options_need_the_multimodal_method(written, tmp_path, capsys):
    _, paths = written
    args = ["register", "--images", *paths, "--method", "affine", "--out", str(tmp_path / "o")]
    assert main([*args, "--strategy", "joint", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--strategy is an option of --method multimodal only" in err
    assert err.count("\n") == 1
