"""End to end: manifests, `nrreval evaluate` on a generated 2D case, ranks, bad manifests."""

from __future__ import annotations

import functools
import json
import math
import re
import tempfile
import warnings

import numpy as np
import pytest
import SimpleITK as sitk
import yaml

import itk_nrreval as nr
from itk_nrreval import InputError
from itk_nrreval.cli import main

N_IMAGES = 6
SIZE = 40


# ----------------------------------------------------------------------------- phantom


def template() -> tuple[np.ndarray, np.ndarray]:
    """A smooth blob phantom (numpy (y, x)) and its label map (0 background, 1..3)."""
    y, x = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    blobs = [((20, 20), (13, 10)), ((14, 17), (4, 3)), ((26, 23), (4, 5))]
    labels = np.zeros((SIZE, SIZE), np.int16)
    for k, ((cy, cx), (ry, rx)) in enumerate(blobs, start=1):
        labels[((y - cy) / ry) ** 2 + ((x - cx) / rx) ** 2 <= 1] = k
    return labels.astype(float), labels


def smooth_field(seed: int, amplitude: float) -> np.ndarray:
    """A smooth displacement (mm), numpy (y, x, 2), zero at the border."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:SIZE, 0:SIZE] / (SIZE - 1)
    bump = np.sin(np.pi * x) * np.sin(np.pi * y)
    out = np.zeros((SIZE, SIZE, 2))
    for c in range(2):
        a, b, p = rng.uniform(-1, 1, 3)
        out[..., c] = amplitude * bump * (a * np.sin(np.pi * (x + p)) + b * np.cos(np.pi * y))
    return out


def image(arr: np.ndarray) -> sitk.Image:
    img = sitk.GetImageFromArray(arr, isVector=arr.ndim == 3)
    img.SetSpacing((1.0, 1.0))
    return img


@functools.cache
def true_field(seed: int, size: int) -> sitk.Image:
    """The inverse of ``smooth_field(seed, 4.0)`` (on the SIZE grid, `size` its key): the
    same in every case, so inverted once per test session (about half of make_case's time,
    and many tests call make_case). Only ever written, never modified."""
    assert size == SIZE
    return sitk.InvertDisplacementField(
        image(smooth_field(seed, 4.0)),
        maximumNumberOfIterations=50,
        maxErrorToleranceThreshold=0.01,
        meanErrorToleranceThreshold=1e-4,
    )


def make_case(tmp_path, *, with_labels: bool = True) -> dict:
    """N images = the phantom (varied contrast) warped by known fields; three registrations.

    Image i is made by resampling the template through S_i (image points -> template
    points); the true registration maps template points to image points, T_i = S_i^-1.
    """
    intensity, labels = template()
    tmpl = image(intensity * 100.0)
    sitk.WriteImage(tmpl, str(tmp_path / "template.nii.gz"))
    lab_img = image(labels)
    rng = np.random.default_rng(0)
    paths = {"images": [], "labels": [], "truth": [], "perturbed": [], "identity": []}
    for i in range(N_IMAGES):
        contrast = intensity * (100.0 + 10 * rng.standard_normal()) + 5 * (labels == 2) * i
        s_i = sitk.DisplacementFieldTransform(image(smooth_field(i, 4.0)))
        img = sitk.Resample(image(contrast), tmpl, s_i, sitk.sitkLinear, 0.0)
        lab = sitk.Resample(lab_img, tmpl, s_i, sitk.sitkNearestNeighbor, 0)
        sitk.WriteImage(img, str(tmp_path / f"img{i}.nii.gz"))
        sitk.WriteImage(lab, str(tmp_path / f"lab{i}.nii.gz"))
        sitk.WriteImage(true_field(i, SIZE), str(tmp_path / f"truth{i}_1Warp.nii.gz"))
        # perturbation acting first (ANTs order [perturbation, truth])
        sitk.WriteImage(image(smooth_field(100 + i, 3.0)), str(tmp_path / f"pert{i}.mha"))
        sitk.WriteTransform(sitk.AffineTransform(2), str(tmp_path / f"id{i}_0GenericAffine.mat"))
        paths["images"].append(f"img{i}.nii.gz")
        paths["labels"].append(f"lab{i}.nii.gz")
        paths["truth"].append(f"truth{i}_1Warp.nii.gz")
        paths["perturbed"].append([f"pert{i}.mha", f"truth{i}_1Warp.nii.gz"])
        paths["identity"].append(f"id{i}_0GenericAffine.mat")
    data = {
        "images": paths["images"],
        "registrations": {
            "truth": {"reference": "template.nii.gz", "transforms": paths["truth"]},
            "perturbed": {"reference": "template.nii.gz", "transforms": paths["perturbed"]},
            "identity": {
                "reference": "img0.nii.gz",
                "reference_index": 0,
                "transforms": paths["identity"],
            },
        },
    }
    if with_labels:
        data["labels"] = paths["labels"]
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return data


# ----------------------------------------------------------------------------- end to end


def test_evaluate_cli_ranks_registrations_by_quality(tmp_path, capsys):
    make_case(tmp_path)
    out = tmp_path / "out"
    code = main(
        [
            "evaluate",
            str(tmp_path / "manifest.yaml"),
            "--out",
            str(out),
            "--samples",
            "3000",
            "--save-resampled",
        ]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "| truth |" in printed and "Specificity" in printed
    res = json.loads((out / "results.json").read_text())
    regs = res["registrations"]
    assert list(regs) == ["truth", "perturbed", "identity"]
    spec = [regs[n]["specificity"]["value"] for n in regs]
    assert spec[0] < spec[1] < spec[2]
    for w in ("inverse_volume", "inverse_volume_complexity", "volume"):
        ov = [regs[n]["overlap"][w] for n in regs]
        assert ov[0] > ov[1] > ov[2], w
        assert [regs[n]["rank"][f"overlap.{w}"] for n in regs] == [1, 2, 3]
    assert [regs[n]["rank"]["specificity"] for n in regs] == [1, 2, 3]
    assert regs["truth"]["relative_rank"]["specificity"] == 100.0
    assert regs["identity"]["relative_rank"]["specificity"] == 0.0
    assert 0 < regs["perturbed"]["relative_rank"]["specificity"] < 100
    # labels were made by nearest-neighbour warping: truth recovers them up to that rounding
    assert regs["truth"]["overlap"]["inverse_volume"] > 0.8
    assert regs["identity"]["frame"]["method"] == "reference_index"
    assert regs["perturbed"]["frame"]["method"] == "mean"
    assert regs["truth"]["frame"] == {
        "method": "common",
        "spread_mean_mm": 0.0,
        "spread_max_mm": 0.0,
    }
    assert res["version"] == nr.__version__ and res["inputs"]["n_images"] == N_IMAGES
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[1].startswith("truth,")
    summary = (out / "summary.md").read_text()
    assert "Overlap (inverse volume)" in summary and "Rel. rank" in summary
    for png in ("specificity.png", "specificity_vs_overlap.png", "mean_images.png"):
        assert (out / png).read_bytes()[:4] == b"\x89PNG"
    saved = sitk.ReadImage(str(out / "resampled" / "truth" / "memberships_000.nii.gz"))
    assert saved.GetNumberOfComponentsPerPixel() == 3  # labels 1..3 (background not stored)
    assert not list(out.rglob(".*tmp*"))


def test_evaluate_python_api_common_random_numbers(tmp_path):
    data = make_case(tmp_path, with_labels=False)
    kw = dict(n_samples=500, seed=3, progress=False)
    a = nr.evaluate(tmp_path / "manifest.yaml", **kw)
    b = nr.evaluate(nr.load_manifest(data, base_dir=tmp_path), **kw)
    assert a.scores["truth"].specificity.value == b.scores["truth"].specificity.value
    assert a.scores["truth"].specificity.seed == a.scores["identity"].specificity.seed == 3
    assert a.measures == ("specificity", "generalization")  # no labels, no overlap
    assert a.mean_images["truth"].shape == (SIZE, SIZE)
    with pytest.raises(ValueError, match="distance: 'l3' is not one of"):
        nr.evaluate(data, distance="l3")
    with pytest.raises(ValueError, match="weightings: 'dice' is not one of"):
        nr.evaluate(data, weightings=["dice"])


# ----------------------------------------------------------------------------- option groups


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: nr.Resampling(interpolation="cubic"), "interpolation: 'cubic' is not one of"),
        (lambda: nr.Resampling(label_interpolation="cubic"), "label_interpolation: 'cubic' is"),
        (
            lambda: nr.Resampling(label_interpolation="gaussian"),
            "label_sigma_mm: label_interpolation='gaussian' needs a finite sigma > 0 mm, got None",
        ),
        (
            lambda: nr.Resampling(label_interpolation="gaussian", label_sigma_mm=math.inf),
            "label_sigma_mm: .* needs a finite sigma",
        ),
        (
            lambda: nr.Resampling(label_sigma_mm=1.0),
            "label_sigma_mm: only with label_interpolation='gaussian', not 'linear'",
        ),
        (lambda: nr.Confidence(samples=1), "samples: expected an integer >= 2, got 1"),
        (lambda: nr.Confidence(samples=True), "samples: expected an integer >= 2, got True"),
        (lambda: nr.Confidence(resamples=2.5), "resamples: expected an integer >= 2, got 2.5"),
        (lambda: nr.Execution(workers=2), r"workers: only with a scheduler \(local or an address"),
        (
            lambda: nr.Execution(scheduler="local", workers=0),
            "workers: expected an integer >= 1, got 0",
        ),
        (lambda: nr.Execution(threads=0), "threads: expected an integer >= 1, got 0"),
        (
            lambda: nr.Execution(scheduler="local", threads=2),
            r"threads: only without a scheduler \(a Dask worker runs one task\)",
        ),
        (
            lambda: nr.Execution(keep_resampled="yes"),
            "keep_resampled: expected True or False, got 'yes'",
        ),
        (
            lambda: nr.evaluate({}, resampling="bspline"),
            r"resampling: expected Resampling\(...\) or None, got str",
        ),
        (
            lambda: nr.evaluate({}, execution={}),
            r"execution: expected Execution\(...\) or None, got dict",
        ),
        (
            lambda: nr.evaluate({}, confidence="yes"),
            "confidence: expected True, False or a Confidence, got str",
        ),
    ],
)
def test_option_groups_refuse_bad_values_naming_the_option(make, message):
    """Each group checks its values when it is made (before any manifest is read: ``{}`` is
    not a valid manifest), and evaluate refuses a group of the wrong type."""
    with pytest.raises(ValueError, match=message):
        make()


def test_option_groups_are_keyword_only_and_frozen():
    for group in (nr.Resampling, nr.Confidence, nr.Execution):
        with pytest.raises(TypeError, match="positional"):
            group(None)
        with pytest.raises(AttributeError):
            group().cache = None  # frozen: a dataclass refuses any assignment
    # the defaults evaluate documents
    assert nr.Resampling() == nr.Resampling(
        interpolation="linear", label_interpolation="linear", label_sigma_mm=None
    )
    assert nr.Execution() == nr.Execution(scheduler=None, workers=None, threads=None, cache=None)
    assert nr.Confidence() == nr.Confidence(samples=None, resamples=None)


def test_confidence_settings_reach_the_jackknife(tmp_path):
    """``confidence=Confidence(resamples=3, samples=...)`` runs the jackknife with 3 groups
    of the 6 subjects and the given samples per replicate; True runs ``Confidence()``:
    leave one subject out (6 groups), ``min(n_samples, 100_000)`` samples."""
    make_case(tmp_path, with_labels=False)
    kw = dict(n_samples=400, seed=3, progress=False)
    default = nr.evaluate(tmp_path / "manifest.yaml", confidence=True, **kw)
    grouped = nr.evaluate(
        tmp_path / "manifest.yaml", confidence=nr.Confidence(resamples=3, samples=300), **kw
    )
    for result, groups, samples in ((default, N_IMAGES, 400), (grouped, 3, 300)):
        assert result.options["confidence"] is True
        assert result.options["resamples"] == groups
        assert result.options["confidence_samples"] == samples
        for scores in result.scores.values():
            assert scores.intervals["specificity"].n_replicates == groups
    # the same main run: only the intervals differ
    for name, scores in grouped.scores.items():
        assert scores.specificity.value == default.scores[name].specificity.value
        assert scores.intervals["specificity"] != default.scores[name].intervals["specificity"]
    off = nr.evaluate(tmp_path / "manifest.yaml", confidence=False, **kw)
    assert off.options["confidence"] is False and off.scores["truth"].intervals == {}


def test_evaluate_writes_nothing_but_a_temporary_cache(tmp_path, monkeypatch):
    """Issue 43: evaluate computes and returns; writing is the result's. Run in a read-only
    working folder, it leaves that folder and its inputs' as they were (every file, size
    and time); its cache, in the system's temporary folder, is gone afterwards. Writing is
    then ``result.write``'s."""
    inputs, work, temp = tmp_path / "inputs", tmp_path / "work", tmp_path / "temp"
    for folder in (inputs, work, temp):
        folder.mkdir()
    make_case(inputs)
    monkeypatch.setattr(tempfile, "tempdir", str(temp))  # the system's temporary folder

    def files() -> dict:
        return {
            str(p): (p.stat().st_size, p.stat().st_mtime_ns)
            for folder in (inputs, work)
            for p in [folder, *folder.rglob("*")]
        }

    before = files()
    work.chmod(0o555)
    monkeypatch.chdir(work)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = nr.evaluate(
                inputs / "manifest.yaml", n_samples=200, confidence=False, progress=False
            )
    finally:
        work.chmod(0o755)
    assert files() == before
    assert list(temp.iterdir()) == []  # the temporary cache, removed
    assert result.to_dict()["registrations"].keys() == {"truth", "perturbed", "identity"}
    written = result.write(tmp_path / "out", figures=False)
    assert {p.name for p in written} >= {"results.json", "results.csv", "summary.md"}


# ----------------------------------------------------------------------------- ranks


def test_ranks_and_relative_ranks_reproduce_paper_table3():
    """Scores from the paper's Table 3 and the ranks / relative ranks printed there."""
    overlap = {"fluid": 0.611, "group": 0.564, "pair1": 0.546, "pair2": 0.553, "affine": 0.335}
    assert nr.ranks(overlap, higher_is_better=True) == {
        "fluid": 1,
        "group": 2,
        "pair1": 4,
        "pair2": 3,
        "affine": 5,
    }
    rel = nr.relative_ranks(overlap, higher_is_better=True)
    assert [round(rel[k], 1) for k in overlap] == [100.0, 83.0, 76.4, 79.0, 0.0]
    spec = {"fluid": 0.131, "group": 0.162, "pair1": 0.173, "pair2": 0.174, "affine": 0.367}
    assert nr.ranks(spec, higher_is_better=False) == {
        "fluid": 1,
        "group": 2,
        "pair1": 3,
        "pair2": 4,
        "affine": 5,
    }
    rel = nr.relative_ranks(spec, higher_is_better=False)
    assert [round(rel[k], 1) for k in spec] == [100.0, 86.9, 82.2, 81.8, 0.0]
    # ties share the better rank (Table 3: both pairwise methods rank 3 at 0.515)
    tied = {"fluid": 0.608, "group": 0.527, "pair1": 0.515, "pair2": 0.515, "affine": 0.301}
    assert list(nr.ranks(tied, higher_is_better=True).values()) == [1, 2, 3, 3, 5]
    assert nr.relative_ranks({"a": 1.0, "b": 1.0}, higher_is_better=True) == {
        "a": 100.0,
        "b": 100.0,
    }
    assert nr.ranks({"a": math.nan, "b": 2.0}, higher_is_better=True) == {"a": None, "b": 1}


# ----------------------------------------------------------------------------- manifests


def test_write_and_add_registration_paths_relative(tmp_path, monkeypatch):
    make_case(tmp_path)
    monkeypatch.chdir(tmp_path)
    target = tmp_path / "sub" / "m.yaml"
    nr.add_registration(
        target,
        "truth",
        reference="template.nii.gz",
        transforms=[f"truth{i}_1Warp.nii.gz" for i in range(N_IMAGES)],
        images=[f"img{i}.nii.gz" for i in range(N_IMAGES)],
    )
    nr.add_registration(
        target,
        "ants",
        reference="img0.nii.gz",
        reference_index=0,
        transforms=[[f"pert{i}.mha", f"id{i}_0GenericAffine.mat"] for i in range(N_IMAGES)],
    )
    nr.add_registration(  # replaces, keeps the order
        target,
        "truth",
        reference="template.nii.gz",
        transforms=[f"truth{i}_1Warp.nii.gz" for i in range(N_IMAGES)],
    )
    raw = yaml.safe_load(target.read_text())
    assert raw["images"][0] == "../img0.nii.gz"
    assert list(raw["registrations"]) == ["truth", "ants"]
    assert raw["registrations"]["ants"]["transforms"][1] == [
        "../pert1.mha",
        "../id1_0GenericAffine.mat",
    ]
    m = nr.load_manifest(target)
    assert m.common_frame == "truth" and m.images[2] == tmp_path / "img2.nii.gz"
    assert m.registrations["ants"].reference_index == 0
    nr.write_manifest(m, tmp_path / "copy.yaml")
    assert nr.load_manifest(tmp_path / "copy.yaml").registrations == m.registrations
    with pytest.raises(InputError, match=r"new\.yaml: manifest does not exist; give images="):
        nr.add_registration(tmp_path / "new.yaml", "x", reference="a", transforms=["b"])


def _bad(tmp_path, edit):
    data = make_case(tmp_path)
    edit(data)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return tmp_path / "bad.yaml"


def _drop_transform(d):
    d["registrations"]["truth"]["transforms"].pop()


def _three_d(tmp_path):
    def edit(d):
        sitk.WriteTransform(sitk.AffineTransform(3), str(tmp_path / "a3.tfm"))
        d["registrations"]["identity"]["transforms"][2] = "a3.tfm"

    return edit


BAD = [
    (
        "missing",
        lambda tp: lambda d: d["images"].__setitem__(1, "nope.nii.gz"),
        r"bad\.yaml: images\[1\]: file not found: .*nope\.nii\.gz$",
    ),
    (
        "count",
        lambda tp: _drop_transform,
        rf"bad\.yaml: registrations\.truth\.transforms: {N_IMAGES - 1} entries for {N_IMAGES} "
        r"images$",
    ),
    (
        "dimension",
        _three_d,
        r"bad\.yaml: registrations\.identity\.transforms\[2\]: 3D transform for 2D images$",
    ),
    (
        "unknown key",
        lambda tp: lambda d: d.update(lables=[]),
        r"bad\.yaml: unknown key 'lables' \(expected images, labels, label_names, groups, "
        r"subjects, evaluation_images, mask, masks, common_frame, registrations\)$",
    ),
    (
        "common frame",
        lambda tp: lambda d: d.update(common_frame="fluid"),
        r"bad\.yaml: common_frame 'fluid' is not a registration "
        r"\(have: truth, perturbed, identity\)$",
    ),
    (
        "labels count",
        lambda tp: lambda d: d["labels"].pop(),
        rf"bad\.yaml: labels: {N_IMAGES - 1} label maps for {N_IMAGES} images$",
    ),
    (
        "reference index",
        lambda tp: lambda d: d["registrations"]["identity"].update(reference_index=9),
        rf"bad\.yaml: registrations\.identity\.reference_index: 9 is not in 0\.\.{N_IMAGES - 1}$",
    ),
]


@pytest.mark.parametrize("case, make_edit, message", BAD, ids=[b[0] for b in BAD])
def test_bad_manifest_one_message_exit_2_no_output(tmp_path, capsys, case, make_edit, message):
    path = _bad(tmp_path, make_edit(tmp_path))
    out = tmp_path / "out"
    code = main(["evaluate", str(path), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("nrreval evaluate: error: ")
    assert re.search(message, lines[0]), lines[0]
    assert not out.exists()
    with pytest.raises(InputError, match=message):
        nr.load_manifest(path)


def test_bad_manifest_lists_every_problem(tmp_path, capsys):
    def edit(d):
        d["images"][0] = "gone.nii.gz"
        d["common_frame"] = "nope"
        d["registrations"]["perturbed"]["extra"] = 1

    path = _bad(tmp_path, edit)
    assert main(["evaluate", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    assert re_count(err) == 3
    assert "bad.yaml: 3 problems: " in err
    assert "gone.nii.gz" in err and "'nope'" in err and "unknown key 'extra'" in err
    assert not (tmp_path / "out").exists()


def re_count(err: str) -> int:
    return int(err.split(" problems: ")[0].rsplit(" ", 1)[1])


def test_unreadable_manifest(tmp_path, capsys):
    (tmp_path / "m.yaml").write_text("images: [a\n")
    assert main(["evaluate", str(tmp_path / "m.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "m.yaml: not valid YAML/JSON" in capsys.readouterr().err
    with pytest.raises(InputError, match=r"missing\.yaml: manifest file not found"):
        nr.load_manifest(tmp_path / "missing.yaml")
