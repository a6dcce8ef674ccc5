"""Evaluating what pipelines wrote: BIDS derivatives, ANTs prefixes, elastix folders (issue 29).

Every tree here is written file by file in the pipelines' own layouts (the BIDS names spelled
out in full below, ANTs and elastix writing their own files), and every manifest the toolkit
finds is checked against one written by hand from those names: same files, same order, and
``evaluate`` gives the same numbers.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk
import yaml

import itk_nrreval as nr
from data_synth import make_population
from itk_nrreval.cli import main
from itk_nrreval.io.transforms import chain_transform, read_transform, write_transform

SPACE = "SynthTemplate"
EVALUATE = ["--samples", "2000", "--no-figures", "--no-confidence", "--quiet"]


# ----------------------------------------------------------------------------- trees


@pytest.fixture(scope="module")
def population():
    """Five 2D subjects with their true transforms (template -> subject)."""
    return make_population("phantom", dim=2, n=5, seed=4, spacing=4.0, size=(52, 60))


def perturbation(grid: sitk.Image, seed: int) -> sitk.DisplacementFieldTransform:
    """A smooth random displacement (up to about 3 mm) on `grid`, zero at its border."""
    rng = np.random.default_rng(seed)
    ny, nx = grid.GetSize()[1], grid.GetSize()[0]
    y, x = np.mgrid[0:ny, 0:nx] / np.array([ny - 1, nx - 1])[:, None, None]
    bump = np.sin(np.pi * x) * np.sin(np.pi * y)
    field = np.stack([3.0 * bump * np.sin(np.pi * (x + rng.uniform())) for _ in range(2)], -1)
    image = sitk.GetImageFromArray(field, isVector=True)
    image.CopyInformation(grid)
    return sitk.DisplacementFieldTransform(image)


def write(image: sitk.Image, path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    sitk.WriteImage(image, str(path))


def write_tree(root, pop, *, version, keys, perturb=False, leave_out=(), pipeline="SynthPrep"):
    """A BIDS derivatives tree of `pop` as fMRIPrep lays its anatomical outputs out.

    `keys`: per subject of `pop`, its (subject, session) labels (session "" for none).
    `perturb`: transforms are the truth after a smooth random perturbation (worse).
    """
    root.mkdir(parents=True)
    description = {
        "Name": "synthetic derivatives",
        "BIDSVersion": "1.8.0",
        "DatasetType": "derivative",
        "GeneratedBy": [{"Name": pipeline, "Version": version}],
    }
    (root / "dataset_description.json").write_text(json.dumps(description))
    for i, (subject, (sub, ses)) in enumerate(zip(pop.subjects, keys, strict=True)):
        if (sub, ses) in leave_out:
            continue
        folder = root / f"sub-{sub}" / (f"ses-{ses}" if ses else "") / "anat"
        stem = f"sub-{sub}" + (f"_ses-{ses}" if ses else "")
        truth = subject.template_to_subject
        xfm = sitk.CompositeTransform([truth, perturbation(pop.template, i)]) if perturb else truth
        write(subject.image, folder / f"{stem}_desc-preproc_T1w.nii.gz")
        (folder / f"{stem}_desc-preproc_T1w.json").write_text("{}")
        write(subject.labels, folder / f"{stem}_dseg.nii.gz")
        write(
            sitk.Cast(subject.labels > 0, sitk.sitkUInt8), folder / f"{stem}_desc-brain_mask.nii.gz"
        )
        write_transform(xfm, folder / f"{stem}_from-T1w_to-{SPACE}_mode-image_xfm.h5")
        # the inverse, as fMRIPrep also writes it: not the one to read
        write_transform(
            subject.subject_to_template, folder / f"{stem}_from-{SPACE}_to-T1w_mode-image_xfm.h5"
        )
        in_space = sitk.Resample(subject.image, pop.template, xfm, sitk.sitkLinear, 0.0)
        write(in_space, folder / f"{stem}_space-{SPACE}_desc-preproc_T1w.nii.gz")
    return root


def anat(root, sub, ses=""):
    """The folder and file-name stem of a subject's anatomical outputs, spelled out."""
    folder = root / f"sub-{sub}" / (f"ses-{ses}" if ses else "") / "anat"
    return folder, f"sub-{sub}" + (f"_ses-{ses}" if ses else "")


def scores(folder) -> dict:
    """Every registration's scores in results.json: name -> flat {field: number}."""
    res = json.loads((folder / "results.json").read_text())
    out = {}
    for name, reg in res["registrations"].items():
        flat = {"specificity": reg["specificity"]["value"]}
        flat["generalization"] = reg["generalization"]["value"]
        flat.update({f"overlap.{k}": v for k, v in (reg.get("overlap") or {}).items()})
        flat.update({f"coverage.{k}": v for k, v in reg["coverage"].items()})
        flat.update({f"frame.{k}": v for k, v in reg["frame"].items() if k != "method"})
        plausibility = reg["plausibility"]
        flat.update({k: v for k, v in plausibility.items() if isinstance(v, float)})
        out[name] = flat
    return out


def assert_same_scores(a: dict, b: dict) -> None:
    assert list(a) == list(b)
    for name in a:
        assert a[name].keys() == b[name].keys(), name
        for key, value in a[name].items():
            assert math.isclose(value, b[name][key], rel_tol=1e-9, abs_tol=1e-12), (name, key)


def run_cli(args, capsys) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


NO_SESSIONS = [(f"{i:02d}", "") for i in range(1, 6)]


# ----------------------------------------------------------------------------- BIDS


def test_two_pipeline_versions_compared_as_a_hand_written_manifest(tmp_path, population, capsys):
    old = write_tree(tmp_path / "old", population, version="1.0", keys=NO_SESSIONS)
    new = write_tree(
        tmp_path / "new",
        population,
        version="2.0",
        keys=NO_SESSIONS,
        perturb=True,
        leave_out=[("03", "")],
    )
    code, _, err = run_cli(["evaluate", old, new, "--out", tmp_path / "auto", *EVALUATE], capsys)
    assert code == 0, err
    # sub-03 is missing from the new folder: said in one line, and left out
    warned = [ln for ln in err.splitlines() if "sub-03" in ln]
    assert warned == [
        f"nrreval evaluate: warning: sub-03: no transform into {SPACE} in {new}; left out"
    ]

    kept = ["01", "02", "04", "05"]
    hand = {
        "images": [str(anat(old, s)[0] / f"sub-{s}_desc-preproc_T1w.nii.gz") for s in kept],
        "labels": [str(anat(old, s)[0] / f"sub-{s}_dseg.nii.gz") for s in kept],
        "registrations": {
            f"SynthPrep-{v}": {
                "reference": str(
                    anat(root, "01")[0] / f"sub-01_space-{SPACE}_desc-preproc_T1w.nii.gz"
                ),
                # one template space: the second pipeline's frame is the common one
                **({"frame_transform": "identity"} if v == "2.0" else {}),
                "transforms": [
                    str(anat(root, s)[0] / f"sub-{s}_from-T1w_to-{SPACE}_mode-image_xfm.h5")
                    for s in kept
                ],
            }
            for v, root in (("1.0", old), ("2.0", new))
        },
    }
    (tmp_path / "hand.yaml").write_text(yaml.safe_dump(hand, sort_keys=False))
    code, _, err = run_cli(
        ["evaluate", tmp_path / "hand.yaml", "--out", tmp_path / "byhand", *EVALUATE], capsys
    )
    assert code == 0, err
    auto, byhand = scores(tmp_path / "auto"), scores(tmp_path / "byhand")
    assert_same_scores(auto, byhand)
    # independent of the finding: the true transforms beat the perturbed ones, and bring the
    # labels together (a transform read the wrong way round would not)
    assert auto["SynthPrep-1.0"]["specificity"] < auto["SynthPrep-2.0"]["specificity"]
    assert auto["SynthPrep-1.0"]["overlap.inverse_volume"] > 0.6
    assert auto["SynthPrep-2.0"]["overlap.inverse_volume"] < 0.5
    # both in the one template space: the second's frame is the common one, not estimated
    # from the two registrations' disagreement (its spread says how far they disagree)
    results = json.loads((tmp_path / "auto" / "results.json").read_text())
    assert results["registrations"]["SynthPrep-2.0"]["frame"]["method"] == "frame_transform"
    assert results["registrations"]["SynthPrep-1.0"]["frame"]["method"] == "common"

    # the same from Python, and `nrreval manifest` writes that manifest
    with pytest.warns(UserWarning, match="sub-03"):
        from_python = nr.manifest_from_derivatives([old, new])
    code, out, err = run_cli(["manifest", old, new, "--out", tmp_path / "m.yaml"], capsys)
    assert code == 0 and "4 images and 2 registrations" in out, err
    expected = nr.load_manifest(tmp_path / "hand.yaml")
    for m in (from_python, nr.load_manifest(tmp_path / "m.yaml")):
        assert_same_files(m, expected)
        assert m.registrations["SynthPrep-2.0"].parameters["generated_by"] == "SynthPrep 2.0"
        # a pipeline of unknown method: no family (the verdict does not weigh roughness)
        assert "method" not in m.registrations["SynthPrep-2.0"].parameters


def assert_same_files(m, expected) -> None:
    """`m` lists the files of `expected`, in its order, under the same names."""
    assert m.images == expected.images and m.labels == expected.labels
    assert m.names == expected.names and m.common_frame == expected.common_frame
    for name, reg in expected.registrations.items():
        assert m.registrations[name].reference == reg.reference, name
        assert m.registrations[name].transforms == reg.transforms, name
        frames = (m.registrations[name].frame_transform, reg.frame_transform)
        assert [getattr(f, "source", f) for f in frames[:1]] == [
            getattr(f, "source", f) for f in frames[1:]
        ], name


@pytest.mark.filterwarnings("ignore:the scores are taken on")
def test_sessions_matched_in_label_order_and_evaluated_from_python(tmp_path, population):
    keys = [("01", "A"), ("01", "B"), ("02", "A"), ("10", "A"), ("02", "B")]
    root = write_tree(tmp_path / "deriv", population, version="1.0", keys=keys)
    ordered = sorted(keys)  # by subject label, then session: 01A 01B 02A 02B 10A
    hand = {
        "images": [
            str(anat(root, *k)[0] / f"{anat(root, *k)[1]}_desc-preproc_T1w.nii.gz") for k in ordered
        ],
        "labels": [str(anat(root, *k)[0] / f"{anat(root, *k)[1]}_dseg.nii.gz") for k in ordered],
        "registrations": {
            "SynthPrep-1.0": {
                "reference": str(
                    anat(root, "01", "A")[0] / f"sub-01_ses-A_space-{SPACE}_desc-preproc_T1w.nii.gz"
                ),
                "transforms": [
                    str(
                        anat(root, *k)[0]
                        / f"{anat(root, *k)[1]}_from-T1w_to-{SPACE}_mode-image_xfm.h5"
                    )
                    for k in ordered
                ],
            }
        },
    }
    found = nr.manifest_from_derivatives([root], space=SPACE)
    assert_same_files(found, nr.load_manifest(hand))
    # a subject's sessions are one subject to the jackknife
    assert found.subjects == ("sub-01", "sub-01", "sub-02", "sub-02", "sub-10")
    kw = dict(n_samples=500, progress=False, confidence=False)
    a = nr.evaluate(found, **kw).scores["SynthPrep-1.0"]
    b = nr.evaluate(hand, **kw).scores["SynthPrep-1.0"]
    assert a.specificity.value == b.specificity.value
    assert a.overlap == b.overlap


@pytest.mark.filterwarnings("ignore:the scores are taken on")
def test_fmriprep_versions_are_settings_of_one_method(tmp_path, population):
    """fMRIPrep and sMRIPrep normalize with ANTs SyN in every version, so two versions of
    them are one family for the verdict (``method: SyN``, ``engine: ants``), which the
    evaluation records; a pipeline of unknown method has none."""
    folders = [
        write_tree(tmp_path / name, population, version=v, keys=NO_SESSIONS, pipeline=name)
        for name, v in (("fMRIPrep", "23.1.0"), ("sMRIPrep", "0.15.0"), ("OtherPrep", "1"))
    ]
    m = nr.manifest_from_derivatives(folders)
    result = nr.evaluate(m, n_samples=200, seed=0, progress=False, confidence=False)
    assert {name: s.family for name, s in result.scores.items()} == {
        "fMRIPrep-23.1.0": ("SyN", "ants"),
        "sMRIPrep-0.15.0": ("SyN", "ants"),
        "OtherPrep-1": None,
    }


# ----------------------------------------------------------------------------- bad trees


def _no_description(root):
    (root / "dataset_description.json").unlink()
    return root / "dataset_description.json", "not found"


def _two_spaces(root):
    folder, stem = anat(root, "02")
    other = folder / f"{stem}_from-T1w_to-MNI152NLin6Asym_mode-image_xfm.h5"
    other.write_bytes((folder / f"{stem}_from-T1w_to-{SPACE}_mode-image_xfm.h5").read_bytes())
    return (
        root,
        f"transforms into more than one space (MNI152NLin6Asym, {SPACE}); choose one with --space",
    )


def _two_transforms(root):
    folder, stem = anat(root, "04")
    xfm = folder / f"{stem}_from-T1w_to-{SPACE}_mode-image_xfm.h5"
    xfm.with_name(f"{stem}_from-T1w_to-{SPACE}_mode-image_desc-other_xfm.h5").write_bytes(
        xfm.read_bytes()
    )
    return (
        folder / f"{stem}_from-T1w_to-{SPACE}_mode-image_desc-other_xfm.h5",
        "two candidate transforms",
    )


def _no_t1w(root):
    folder, stem = anat(root, "05")
    (folder / f"{stem}_desc-preproc_T1w.nii.gz").unlink()
    return (
        folder / f"{stem}_from-T1w_to-{SPACE}_mode-image_xfm.h5",
        "a transform without its T1w image",
    )


def _other_grid(root):
    folder, stem = anat(root, "02")
    path = folder / f"{stem}_space-{SPACE}_desc-preproc_T1w.nii.gz"
    image = sitk.ReadImage(str(path))
    sitk.WriteImage(sitk.Shrink(image, [2, 2]), str(path))
    return path, "not on the grid of"


BAD_TREES = [_no_description, _two_spaces, _two_transforms, _no_t1w, _other_grid]


@pytest.mark.parametrize("spoil", BAD_TREES, ids=[f.__name__[1:] for f in BAD_TREES])
@pytest.mark.parametrize("command", ["manifest", "evaluate"])
def test_bad_tree_one_line_naming_the_file(tmp_path, population, capsys, spoil, command):
    root = write_tree(tmp_path / "deriv", population, version="1.0", keys=NO_SESSIONS)
    named, problem = spoil(root)
    out = tmp_path / ("m.yaml" if command == "manifest" else "out")
    code, _, err = run_cli([command, root, "--out", out], capsys)
    assert code == 2
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"nrreval {command}: error: {named}"), lines[0]
    assert problem in lines[0]
    assert not out.exists()


def test_bad_arguments_one_line(tmp_path, population, capsys):
    root = write_tree(tmp_path / "deriv", population, version="1.0", keys=NO_SESSIONS)
    manifest, out = tmp_path / "m.yaml", tmp_path / "o"
    manifest.write_text("images: []\n")
    cases = [
        (["manifest", "--out", tmp_path / "x.yaml"], "nothing to read"),
        (
            ["manifest", root, "--space", "MNI152NLin6Asym", "--out", tmp_path / "x.yaml"],
            f"{root}: no from-T1w_to-MNI152NLin6Asym",
        ),
        (["manifest", root, "--ants", "x/sub-*_", "--out", tmp_path / "x.yaml"], "not both"),
        (["manifest", root, "--method", "a=SyN", "--out", tmp_path / "x.yaml"], "--method goes"),
        (["manifest", "--ants", "x/sub-*_", "--out", tmp_path / "x.yaml"], "need --images"),
        (["evaluate", manifest, root, "--out", out], "m.yaml: give one manifest file"),
        (["evaluate", manifest, "--space", SPACE, "--out", out], "--space goes with"),
        (["evaluate", tmp_path / "nope", "--out", out], "nope: manifest file not found"),
        (["evaluate", root, tmp_path / "nope", "--out", out], "nope: not found (expected a"),
    ]
    for args, message in cases:
        code, _, err = run_cli(args, capsys)
        assert code == 2 and len(err.strip().splitlines()) == 1 and message in err, (args, err)


def test_manifest_never_replaces_a_file_it_did_not_write(tmp_path, population, capsys):
    root = write_tree(tmp_path / "deriv", population, version="1.0", keys=NO_SESSIONS)
    mine = tmp_path / "notes.yaml"
    mine.write_text("my notes\n")
    code, _, err = run_cli(["manifest", root, "--out", mine], capsys)
    assert code == 2 and "exists and was not written by nrreval" in err
    assert mine.read_text() == "my notes\n"
    # a manifest it wrote is its own: written again (after the user's edit) without a word
    ours = tmp_path / "m.yaml"
    assert run_cli(["manifest", root, "--out", ours], capsys)[0] == 0
    assert ours.read_text().startswith("# written by itk-nrreval")
    ours.write_text(ours.read_text().replace("SynthPrep-1.0", "edited"))
    assert run_cli(["manifest", root, "--out", ours], capsys)[0] == 0
    assert "edited" not in ours.read_text()
    # nor one of the files it reads
    t1w = anat(root, "01")[0] / "sub-01_desc-preproc_T1w.nii.gz"
    code, _, err = run_cli(["manifest", root, "--out", t1w], capsys)
    assert code == 2 and "is one of the inputs" in err


# ----------------------------------------------------------------------------- ANTs, elastix


def write_subjects(folder, pop) -> list[str]:
    """Images, label maps and the template as a user's folder holds them; the labels."""
    labels = [f"{i:02d}" for i in range(1, len(pop) + 1)]
    for label, subject in zip(labels, pop.subjects, strict=True):
        write(subject.image, folder / "img" / f"sub-{label}_T1w.nii.gz")
        write(subject.labels, folder / "lab" / f"sub-{label}_dseg.nii.gz")
    write(pop.template, folder / "template.nii.gz")
    return labels


def hand_manifest(folder, labels, registrations) -> dict:
    return {
        "images": [str(folder / "img" / f"sub-{s}_T1w.nii.gz") for s in labels],
        "labels": [str(folder / "lab" / f"sub-{s}_dseg.nii.gz") for s in labels],
        "registrations": {
            name: {"reference": str(folder / "template.nii.gz"), "transforms": transforms}
            for name, transforms in registrations.items()
        },
    }


def test_ants_prefixes_read_as_written_by_ants(tmp_path, population, capsys, monkeypatch):
    ants = pytest.importorskip("ants")
    monkeypatch.chdir(tmp_path)
    labels = write_subjects(tmp_path, population)
    fixed = ants.image_read("template.nii.gz")
    warped = {}
    for s in labels:
        moving = ants.image_read(f"img/sub-{s}_T1w.nii.gz")
        (tmp_path / "ants").mkdir(exist_ok=True)
        result = ants.registration(
            fixed, moving, "SyN", outprefix=f"ants/sub-{s}_", reg_iterations=(20, 10, 0)
        )
        warped[s] = result["warpedmovout"].numpy().T  # ANTs (x, y) -> numpy (y, x)
    args = ["--images", "img/sub-*_T1w.nii.gz", "--labels", "lab/sub-*_dseg.nii.gz"]
    args += ["--reference", "template.nii.gz", "--ants", "syn=ants/sub-*_"]
    code, _, err = run_cli(["manifest", *args, "--out", "m.yaml"], capsys)
    assert code == 0, err
    chains = {
        "syn": [
            [
                str(tmp_path / f"ants/sub-{s}_1Warp.nii.gz"),
                str(tmp_path / f"ants/sub-{s}_0GenericAffine.mat"),
            ]
            for s in labels
        ]
    }
    (tmp_path / "hand.yaml").write_text(yaml.safe_dump(hand_manifest(tmp_path, labels, chains)))
    assert_same_files(nr.load_manifest("m.yaml"), nr.load_manifest("hand.yaml"))
    # a warp does not say whether SyN wrote it: the engine alone
    assert nr.load_manifest("m.yaml").registrations["syn"].parameters == {"engine": "ants"}
    # independent of the reading: the chain resamples each image as ANTs itself did
    m = nr.load_manifest("m.yaml")
    template = sitk.ReadImage("template.nii.gz")
    for s, chain in zip(labels, m.registrations["syn"].transforms, strict=True):
        image = sitk.ReadImage(f"img/sub-{s}_T1w.nii.gz", sitk.sitkFloat32)
        ours = sitk.GetArrayFromImage(sitk.Resample(image, template, chain_transform(chain)))
        assert np.abs(ours - warped[s]).max() < 1e-3 * np.abs(warped[s]).max(), s
    for name in ("m.yaml", "hand.yaml"):
        assert run_cli(["evaluate", name, "--out", f"out-{name}", *EVALUATE], capsys)[0] == 0
    assert_same_scores(scores(tmp_path / "out-m.yaml"), scores(tmp_path / "out-hand.yaml"))


ELASTIX_SCRIPT = """
import sys, os
import itk

fixed = itk.imread("template.nii.gz", itk.F)
po = itk.ParameterObject.New()
affine = po.GetDefaultParameterMap("affine", 2)
bspline = po.GetDefaultParameterMap("bspline", 2, 16.0)
for pm in (affine, bspline):
    pm["MaximumNumberOfIterations"] = ["40"]
po.AddParameterMap(affine)
po.AddParameterMap(bspline)
for label in sys.argv[1:]:
    moving = itk.imread(f"img/sub-{label}_T1w.nii.gz", itk.F)
    out = f"elx/sub-{label}"  # relative: elastix records the first run's file as such
    os.makedirs(out)
    _, result = itk.elastix_registration_method(
        fixed, moving, parameter_object=po, output_directory=out, log_to_console=False
    )
    # elastix's own mapping of the fixed grid, for the test to compare with
    field = itk.transformix_deformation_field(moving, result)
    itk.imwrite(field, f"field-{label}.nii.gz")
"""


def test_elastix_folders_read_as_written_by_elastix(tmp_path, population, capsys, monkeypatch):
    pytest.importorskip("itk")
    from itk_nrreval.experiments.registration._elastix_worker import elastix_available

    if not elastix_available():
        pytest.skip("itk-elastix is not installed")
    monkeypatch.chdir(tmp_path)
    labels = write_subjects(tmp_path, population)[:4]
    # itk-elastix in its own process (about 1 GB, and it can crash its process); transformix
    # writes into the working directory: this test's folder
    subprocess.run([sys.executable, "-c", ELASTIX_SCRIPT, *labels], check=True, cwd=tmp_path)
    first = (tmp_path / "elx/sub-01/TransformParameters.1.txt").read_text()
    assert '(InitialTransformParameterFileName "elx/sub-01/TransformParameters.0.txt")' in first

    args = ["--images", "img/sub-*_T1w.nii.gz", "--labels", "lab/sub-*_dseg.nii.gz"]
    args += ["--reference", "template.nii.gz", "--elastix", "elx/sub-*/"]
    code, _, err = run_cli(["manifest", *args, "--out", "m.yaml"], capsys)
    assert code == 0, err
    assert err.strip() == (
        f"nrreval manifest: warning: {tmp_path}/img/sub-05_T1w.nii.gz: no transform in elastix; "
        "left out"
    )
    last = {"elastix": [str(tmp_path / f"elx/sub-{s}/TransformParameters.1.txt") for s in labels]}
    (tmp_path / "hand.yaml").write_text(yaml.safe_dump(hand_manifest(tmp_path, labels, last)))
    assert_same_files(nr.load_manifest("m.yaml"), nr.load_manifest("hand.yaml"))
    # independent of the reading: the affine and B-spline, chained, map the fixed grid as
    # transformix does
    template = sitk.ReadImage("template.nii.gz")
    for s in labels:
        transform = read_transform(tmp_path / f"elx/sub-{s}/TransformParameters.1.txt")
        ours = sitk.GetArrayFromImage(
            sitk.TransformToDisplacementField(
                transform,
                sitk.sitkVectorFloat64,
                template.GetSize(),
                template.GetOrigin(),
                template.GetSpacing(),
                template.GetDirection(),
            )
        )
        theirs = sitk.GetArrayFromImage(sitk.ReadImage(f"field-{s}.nii.gz"))
        assert np.abs(ours - theirs).max() < 1e-3, s  # mm
        assert np.abs(theirs).max() > 1.0  # a registration that moved something
    for name in ("m.yaml", "hand.yaml"):
        assert run_cli(["evaluate", name, "--out", f"out-{name}", *EVALUATE], capsys)[0] == 0
    assert_same_scores(scores(tmp_path / "out-m.yaml"), scores(tmp_path / "out-hand.yaml"))
    # the last parameter file names the B-spline as its Transform: the registration's method,
    # which the evaluation records as its family (the hand-written manifest gives none)
    named = re.search(r'\(Transform "(\w+)"\)', first)
    assert named is not None and "BSpline" in named.group(1)
    family = {
        name: json.loads((tmp_path / f"out-{name}" / "results.json").read_text())["registrations"][
            "elastix"
        ]["family"]
        for name in ("m.yaml", "hand.yaml")
    }
    assert family == {"m.yaml": [named.group(1), "elastix"], "hand.yaml": None}


def test_elastix_chain_by_hand(tmp_path):
    """Parameter files written as elastix writes them, their mapping worked out by hand."""
    from itk_nrreval.io._cache import content_digest

    folder = tmp_path / "moved"
    folder.mkdir()
    euler = folder / "TransformParameters.0.txt"
    entries = [
        '(Transform "EulerTransform")',
        "(NumberOfParameters 3)",
        "(TransformParameters 0.1 1 2)",
        '(InitialTransformParameterFileName "NoInitialTransform")',
        '(HowToCombineTransforms "Compose")',
        "(FixedImageDimension 2)",
        "(MovingImageDimension 2)",
        "(CenterOfRotationPoint 3 4)",
        "// a comment, as elastix writes them",
    ]
    euler.write_text("\n".join(entries) + "\n")
    shift = folder / "TransformParameters.1.txt"
    shift.write_text(
        '(Transform "TranslationTransform")\n(TransformParameters 5 6)\n'
        # recorded where elastix ran, before the folder was moved
        '(InitialTransformParameterFileName "/elsewhere/out/TransformParameters.0.txt")\n'
        "(FixedImageDimension 2)\n"
    )
    p = np.array([10.0, -3.0])
    c, angle = np.array([3.0, 4.0]), 0.1
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    expected = rotation @ (p - c) + c + np.array([1.0, 2.0]) + np.array([5.0, 6.0])
    transform = read_transform(shift)
    assert np.allclose(transform.TransformPoint(tuple(p)), expected, atol=1e-12)
    # the cache key of the last file follows the first one's content
    before = content_digest(shift)
    euler.write_text(euler.read_text().replace("0.1 1 2", "0.1 1 3"))
    assert content_digest(shift) != before
    # an ITK text transform is not taken for an elastix file
    itk_text = tmp_path / "affine.txt"
    sitk.WriteTransform(sitk.TranslationTransform(2, (1.0, 2.0)), str(itk_text))
    assert read_transform(itk_text).TransformPoint((0.0, 0.0)) == (1.0, 2.0)
    # elastix files without their initial one, or of a kind not read: one line naming the file
    euler.unlink()
    with pytest.raises(nr.InputError, match=r"TransformParameters\.1\.txt: its initial transform"):
        read_transform(shift)
    shift.write_text('(Transform "AffineDTITransform")\n(FixedImageDimension 2)\n')
    with pytest.raises(
        nr.InputError, match=r"\.1\.txt: elastix AffineDTITransform transform is not"
    ):
        read_transform(shift)
