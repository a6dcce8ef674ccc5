"""Issue 44, items 2, 5, 10 and 14: `register` never replaces a registration unasked, a broken
HDF5 transform is one line with nothing from HDF5's C library, `manifest` writes the identity
frame for registrations sharing the common frame's reference, and the messages for a glob the
shell expanded and for the registration `validate` perturbs.

Everything is read from and written to real files by SimpleITK, on small 2D grids with an
origin and a spacing that are not the defaults (seconds each).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml

from itk_nrreval import InputError
from itk_nrreval.cli import main
from itk_nrreval.io.manifest import IDENTITY_FRAME, load_manifest, write_manifest
from itk_nrreval.io.pipeline_outputs import manifest_from_transforms
from itk_nrreval.io.transforms import read_transform, transform_pieces

ORIGIN = (-31.5, 12.25)  # mm, ITK (x, y)
SPACING = (1.25, 0.8)
SIZE = (26, 30)  # ITK (x, y)


def on_grid(array: np.ndarray) -> sitk.Image:
    image = sitk.GetImageFromArray(array)
    image.SetOrigin(ORIGIN)
    image.SetSpacing(SPACING)
    return image


def blob(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Image i and its label map (numpy order): two blocks, moved a pixel per image."""
    labels = np.zeros(SIZE[::-1], np.uint8)
    labels[8 + i : 18 + i, 5:14] = 1
    labels[12:20, 15 + i : 22 + i] = 2
    rng = np.random.default_rng(i)
    image = 100.0 * (labels == 1) + 60.0 * (labels == 2) + rng.normal(0, 3, labels.shape)
    return image.astype(np.float32), labels


def write_images(folder: Path, n: int = 3, *, stem: str = "s", labels: bool = False) -> list[str]:
    """n images (and label maps ``<stem><i>_lab.nii.gz``) in `folder`; the image paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        image, lab = blob(i)
        paths.append(str(folder / f"{stem}{i}.nii.gz"))
        sitk.WriteImage(on_grid(image), paths[-1])
        if labels:
            sitk.WriteImage(on_grid(lab), str(folder / f"{stem}{i}_lab.nii.gz"))
    return paths


def shift(i: int) -> sitk.AffineTransform:
    """A small affine map, different per image (reference -> image)."""
    t = sitk.AffineTransform(2)
    t.SetCenter((ORIGIN[0] + 15.0, ORIGIN[1] + 12.0))
    t.SetMatrix((1.0 + 0.01 * i, 0.02, -0.01, 1.0))
    t.SetTranslation((0.4 * i, -0.3))
    return t


def one_line_error(err: str, command: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"nrreval {command}: error: "), err
    return lines[0]


# ----------------------------------------------------------------------------- item 2


@pytest.fixture
def registered(tmp_path):
    """Images and an nrreval manifest with registrations 'affine' and 'fluid' (files on disk)."""
    paths = write_images(tmp_path / "img")
    for name in ("affine", "fluid"):
        (tmp_path / name).mkdir()
        for i in range(len(paths)):
            sitk.WriteTransform(shift(i), str(tmp_path / name / f"{i}.tfm"))
    regs = {
        name: {
            "reference": paths[0],
            "transforms": [str(tmp_path / name / f"{i}.tfm") for i in range(len(paths))],
        }
        for name in ("affine", "fluid")
    }
    manifest = write_manifest({"images": paths, "registrations": regs}, tmp_path / "m.yaml")
    return manifest, paths


def tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.mark.parametrize("name", [None, "affine"])
def test_register_refuses_to_replace_a_registration_of_the_manifest(
    registered, tmp_path, capsys, name
):
    """`register` into a manifest that already has a registration of that name (given with
    --name, or the method's default name) is refused before any work: one line naming the
    manifest and the name, exit 2, nothing written."""
    manifest, paths = registered
    before = tree(tmp_path)
    out = tmp_path / "new"
    args = ["register", "--images", *paths, "--method", "affine", "--manifest", str(manifest)]
    args += ["--out", str(out), "--no-progress", *(["--name", name] if name else [])]
    assert main(args) == 2
    line = one_line_error(capsys.readouterr().err, "register")
    assert str(manifest) in line and "'affine'" in line and "--replace" in line
    assert tree(tmp_path) == before and not out.exists()


def test_register_replace_replaces_only_that_registration(registered, tmp_path, capsys):
    manifest, paths = registered
    out = tmp_path / "new"
    args = ["register", "--images", *paths, "--method", "affine", "--manifest", str(manifest)]
    assert main([*args, "--out", str(out), "--no-progress", "--replace"]) == 0, capsys.readouterr()
    m = load_manifest(manifest)
    assert list(m.registrations) == ["affine", "fluid"]  # in place, the other one kept
    assert all(Path(c[0]).parent == out for c in m.registrations["affine"].transforms)
    assert m.registrations["fluid"].transforms[0][0] == tmp_path / "fluid" / "0.tfm"
    # a new name needs no --replace
    assert main([*args, "--out", str(tmp_path / "b"), "--no-progress", "--name", "b"]) == 0
    assert list(load_manifest(manifest).registrations) == ["affine", "fluid", "b"]


def test_register_help_documents_replace(capsys):
    assert main(["register", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--replace" in text and "replace the manifest's registration of that name" in text


# ----------------------------------------------------------------------------- item 5


def truncated_h5(path: Path, transform: sitk.Transform) -> Path:
    """`transform` written by SimpleITK to `path`, then cut in half."""
    sitk.WriteTransform(transform, str(path))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def field(i: int) -> sitk.DisplacementFieldTransform:
    """A displacement field on the images' grid: what a non-rigid registration writes."""
    rng = np.random.default_rng(10 + i)
    values = rng.normal(0, 0.3, (*SIZE[::-1], 2))
    image = sitk.GetImageFromArray(values, isVector=True)
    image.SetOrigin(ORIGIN)
    image.SetSpacing(SPACING)
    return sitk.DisplacementFieldTransform(image)


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """`nrreval` in its own process: what the C libraries print on stderr is seen too."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    code = "import sys; from itk_nrreval.cli import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, cwd=cwd, env=env
    )


def test_truncated_h5_transform_is_one_line_without_hdf5_diagnostics(tmp_path):
    """`evaluate` and `manifest` of a manifest / ANTs prefix whose .h5 was cut in half: one
    line naming the file, exit 2, nothing from HDF5's C library (its HDF5-DIAG stack)."""
    paths = write_images(tmp_path / "img", stem="sub-0")
    (tmp_path / "ants").mkdir()
    transforms = []
    for i in range(len(paths)):
        composite = sitk.CompositeTransform([shift(i), field(i)])
        transforms.append(tmp_path / "ants" / f"sub-0{i}_Composite.h5")
        sitk.WriteTransform(composite, str(transforms[-1]))
    truncated_h5(transforms[1], sitk.CompositeTransform([shift(1), field(1)]))
    manifest = tmp_path / "m.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {
                "images": paths,
                "registrations": {
                    "a": {"reference": paths[0], "transforms": [str(t) for t in transforms]}
                },
            }
        )
    )
    runs = {
        "evaluate": ["evaluate", str(manifest), "--out", "o", "--samples", "200", "--quiet"],
        "manifest": [
            "manifest",
            "--images",
            "img/sub-*.nii.gz",
            "--reference",
            paths[0],
            "--ants",
            "ants/sub-*_",
            "--out",
            "new.yaml",
        ],
    }
    for command, args in runs.items():
        done = run_cli(args, tmp_path)
        assert done.returncode == 2, done.stderr
        line = one_line_error(done.stderr, command)
        assert "HDF5" not in done.stderr.replace("HDF5 file", "")
        assert transforms[1].name in line and "truncated" in line, line
    assert not (tmp_path / "o").exists() and not (tmp_path / "new.yaml").exists()


@pytest.mark.parametrize(
    ("spoil", "problem"),
    [
        (
            "truncated",
            r"sub-01\.h5: cannot read transform \(truncated HDF5 file: \d+ of its \d+ bytes",
        ),
        ("damaged", r"sub-01\.h5: cannot read transform \(damaged HDF5 file: incorrect"),
        ("empty", r"sub-01\.h5: cannot read transform \(not an HDF5 file"),
        ("text", r"sub-01\.h5: cannot read transform \(not an HDF5 file"),
    ],
)
def test_broken_h5_read_in_process_is_one_input_error_and_silent(tmp_path, capfd, spoil, problem):
    """read_transform and transform_pieces (a transform's own reading, not the manifest
    check's) refuse a broken .h5 with an InputError naming it; HDF5's C library prints
    nothing on the process's stderr (file descriptor 2)."""
    path = tmp_path / "sub-01.h5"
    if spoil == "truncated":
        truncated_h5(path, sitk.CompositeTransform([shift(1), field(1)]))
    elif spoil == "damaged":  # one byte of the last object header: its checksum fails
        sitk.WriteTransform(sitk.CompositeTransform([shift(1), field(1)]), str(path))
        data = bytearray(path.read_bytes())
        data[data.rindex(b"OHDR") + 8] ^= 0xFF
        path.write_bytes(bytes(data))
    else:
        path.write_bytes(b"" if spoil == "empty" else b"#Insight Transform File V1.0\n")
    for reader in (read_transform, transform_pieces, lambda p: transform_pieces([p, p])):
        with pytest.raises(InputError, match=problem) as err:
            reader(path)
        assert "\n" not in str(err.value)
    captured = capfd.readouterr()
    assert captured.err == "" and captured.out == ""


def test_whole_h5_transforms_still_read(tmp_path, capfd):
    """The check before ITK's reading lets ITK's HDF5 files through: an affine map, a
    displacement field, a composite, and a B-spline (a layout h5py's reading of the pieces
    leaves to ITK), each mapping points as the transform written."""
    bspline = sitk.BSplineTransformInitializer(on_grid(blob(0)[0]), [3, 3])
    bspline.SetParameters(np.linspace(-1.0, 1.0, bspline.GetNumberOfParameters()).tolist())
    written = {
        "a.h5": shift(1),
        "f.hdf5": field(1),
        "c.h5": sitk.CompositeTransform([shift(2), field(2)]),
        "b.h5": bspline,
    }
    point = (ORIGIN[0] + 9.1, ORIGIN[1] + 7.3)
    for name, t in written.items():
        sitk.WriteTransform(t, str(tmp_path / name))
        for read in (read_transform(tmp_path / name), transform_pieces(tmp_path / name)):
            mapped = sitk.CompositeTransform(list(read)) if isinstance(read, tuple) else read
            assert np.allclose(mapped.TransformPoint(point), t.TransformPoint(point), atol=1e-9)
    assert capfd.readouterr().err == ""


# ----------------------------------------------------------------------------- item 10


def write_pipelines(folder: Path, n: int = 3) -> None:
    """Images, a template, two ANTs prefixes and one elastix folder per subject, as the tools
    lay them out (ANTs: ``<prefix>0GenericAffine.mat`` and ``<prefix>1Warp.nii.gz``;
    elastix: ``TransformParameters.0.txt``), written by SimpleITK / by hand."""
    for i, image_path in enumerate(write_images(folder / "img", n, stem="sub-0")):
        os.replace(image_path, folder / "img" / f"sub-0{i}_T1w.nii.gz")
        for prefix in ("ants", "syn"):
            (folder / prefix).mkdir(exist_ok=True)
            sitk.WriteTransform(shift(i), str(folder / prefix / f"sub-0{i}_0GenericAffine.mat"))
            warp = sitk.Image(field(i).GetDisplacementField())
            sitk.WriteImage(warp, str(folder / prefix / f"sub-0{i}_1Warp.nii.gz"))
        elx = folder / "elx" / f"sub-0{i}"
        elx.mkdir(parents=True)
        (elx / "TransformParameters.0.txt").write_text(
            '(Transform "TranslationTransform")\n(NumberOfParameters 2)\n'
            f"(TransformParameters {0.5 * i} -0.25)\n"
            '(InitialTransformParameterFileName "NoInitialTransform")\n'
            '(HowToCombineTransforms "Compose")\n(FixedImageDimension 2)\n'
            "(MovingImageDimension 2)\n"
        )
    sitk.WriteImage(on_grid(blob(0)[0]), str(folder / "template.nii.gz"))


def test_manifest_of_pipelines_sharing_the_reference_writes_the_identity_frame(
    tmp_path, capsys, monkeypatch
):
    """Every registration after the first (the common frame) has the same reference, the
    template: its frame is the common frame, written `frame_transform: identity` (so no
    frame is estimated), as the derivatives path writes it."""
    write_pipelines(tmp_path)
    monkeypatch.chdir(tmp_path)
    args = ["manifest", "--images", "img/sub-*_T1w.nii.gz", "--reference", "template.nii.gz"]
    args += ["--ants", "ants/sub-*_", "--ants", "syn=syn/sub-*_", "--elastix", "elx/sub-*/"]
    assert main([*args, "--out", "m.yaml"]) == 0, capsys.readouterr().err
    written = yaml.safe_load((tmp_path / "m.yaml").read_text())
    regs = written["registrations"]
    assert list(regs) == ["ants", "syn", "elastix"] and written["common_frame"] == "ants"
    assert "frame_transform" not in regs["ants"]
    assert regs["syn"]["frame_transform"] == regs["elastix"]["frame_transform"] == IDENTITY_FRAME
    m = load_manifest(tmp_path / "m.yaml")
    assert m.registrations["elastix"].frame_transform.source == IDENTITY_FRAME
    # the Python function writes the same
    same = manifest_from_transforms(
        images="img/sub-*_T1w.nii.gz",
        reference="template.nii.gz",
        ants={"ants": "ants/sub-*_", "syn": "syn/sub-*_"},
        elastix="elx/sub-*/",
    )
    assert [r.frame_transform is None for r in same.registrations.values()] == [True, False, False]


@pytest.mark.filterwarnings("ignore:registration 'ants' is flagged as implausible")
def test_manifest_records_each_engine_and_the_method_its_files_name(tmp_path, capsys, monkeypatch):
    """The verdict weighs roughness against specificity only between settings of one method
    (the same ``method`` and ``engine`` in a registration's ``parameters``). `manifest` records
    every registration's engine, and its method where its files name one: an elastix folder's
    ``Transform``, an ANTs chain without a warp (affine). A warp does not say whether SyN or
    B-spline SyN wrote it: the command says how to give the method, and ``--method`` records
    it, which the evaluation reads as the registration's family."""
    import itk_nrreval as nr

    write_pipelines(tmp_path)
    for i in range(3):  # an ANTs registration that stopped at its affine stage
        (tmp_path / "lin").mkdir(exist_ok=True)
        affine = (tmp_path / "ants" / f"sub-0{i}_0GenericAffine.mat").read_bytes()
        (tmp_path / "lin" / f"sub-0{i}_0GenericAffine.mat").write_bytes(affine)
    monkeypatch.chdir(tmp_path)
    args = ["manifest", "--images", "img/sub-*_T1w.nii.gz", "--reference", "template.nii.gz"]
    args += ["--ants", "ants/sub-*_", "--ants", "lin=lin/sub-*_", "--elastix", "elx/sub-*/"]
    assert main([*args, "--out", "m.yaml"]) == 0
    out = capsys.readouterr().out
    regs = yaml.safe_load((tmp_path / "m.yaml").read_text())["registrations"]
    assert {name: reg["parameters"] for name, reg in regs.items()} == {
        "ants": {"engine": "ants"},
        "lin": {"engine": "ants", "method": "affine"},
        "elastix": {"engine": "elastix", "method": "TranslationTransform"},
    }
    assert "the files of ants do not say which method wrote them" in out
    assert "--method ants=METHOD" in out

    assert main([*args, "--method", "ants=SyN", "--out", "m2.yaml"]) == 0
    assert "do not say" not in capsys.readouterr().out
    result = nr.evaluate(
        tmp_path / "m2.yaml", n_samples=50, seed=0, progress=False, confidence=False
    )
    assert {name: s.family for name, s in result.scores.items()} == {
        "ants": ("SyN", "ants"),
        "lin": ("affine", "ants"),
        "elastix": ("TranslationTransform", "elastix"),
    }


@pytest.mark.parametrize(
    ("method", "message"),
    [
        ("nope=SyN", "--method nope=SyN: no registration named 'nope' (there are ants, elastix)"),
        ("ants", "--method ants: give NAME=METHOD"),
    ],
)
def test_manifest_method_of_no_registration_is_one_line(
    tmp_path, capsys, monkeypatch, method, message
):
    write_pipelines(tmp_path)
    monkeypatch.chdir(tmp_path)
    args = ["manifest", "--images", "img/sub-*_T1w.nii.gz", "--reference", "template.nii.gz"]
    args += ["--ants", "ants/sub-*_", "--elastix", "elx/sub-*/", "--method", method]
    assert main([*args, "--out", "m.yaml"]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "m.yaml").exists()


def test_method_written_needs_every_subject_to_name_the_same(tmp_path):
    """Subjects whose elastix files name different transforms give no method: the
    registration is not one method's."""
    from itk_nrreval.io._transform_patterns import method_written

    chains = {}
    for i, transform in enumerate(("BSplineTransform", "BSplineTransform", "AffineTransform")):
        path = tmp_path / f"TransformParameters.{i}.txt"
        path.write_text(f'(Transform "{transform}")\n(NumberOfParameters 0)\n')
        chains[(f"{i}",)] = [path]
    assert method_written("elastix", dict(list(chains.items())[:2])) == "BSplineTransform"
    assert method_written("elastix", chains) is None


# ----------------------------------------------------------------------------- item 14


@pytest.mark.parametrize(
    ("expanded", "example"),
    [
        ("--images", "--images 'img/sub-*_T1w.nii.gz'"),
        ("--elastix", "--elastix 'elx/sub-*/'"),
        ("--labels", "--labels 'lab/sub-*_dseg.nii.gz'"),
    ],
)
def test_manifest_names_a_pattern_the_shell_expanded(
    tmp_path, capsys, monkeypatch, expanded, example
):
    """An unquoted pattern reaches nrreval as many arguments (what the shell expanded it
    into), the first the option's value and the others taken for derivatives folders: the
    message says so and how to quote it (the pattern the paths came from), not 'not both';
    nothing is written."""
    write_pipelines(tmp_path)
    for i in range(3):
        (tmp_path / "lab").mkdir(exist_ok=True)
        sitk.WriteImage(on_grid(blob(i)[1]), str(tmp_path / "lab" / f"sub-0{i}_dseg.nii.gz"))
    monkeypatch.chdir(tmp_path)
    patterns = {
        "--images": "img/sub-*_T1w.nii.gz",
        "--elastix": "elx/sub-*/",
        "--labels": "lab/sub-*_dseg.nii.gz",
        "--reference": "template.nii.gz",
        "--ants": "ants/sub-*_",
    }
    args = ["manifest"]
    for name, pattern in patterns.items():
        # what the shell passes for an unquoted pattern: its matches, sorted
        values = sorted(str(p) + ("/" if p.is_dir() else "") for p in Path().glob(pattern))
        args += [name, *(values if name == expanded else [pattern])]
    assert main([*args, "--out", "m.yaml"]) == 2
    line = one_line_error(capsys.readouterr().err, "manifest")
    assert "not both" not in line
    assert f"{expanded} " in line and "your shell expanded into 3 paths" in line, line
    assert f"quote it, e.g. {example}" in line, line
    assert not (tmp_path / "m.yaml").exists()


def test_manifest_pattern_expanded_to_one_path_says_to_quote_it(tmp_path, capsys, monkeypatch):
    """A pattern the shell expanded into one path (one subject) is one argument without a *:
    the message says to quote it."""
    write_pipelines(tmp_path, 1)
    monkeypatch.chdir(tmp_path)
    args = ["manifest", "--images", "img/sub-00_T1w.nii.gz", "--reference", "template.nii.gz"]
    assert main([*args, "--ants", "ants/sub-*_", "--out", "m.yaml"]) == 2
    line = one_line_error(capsys.readouterr().err, "manifest")
    assert "--images img/sub-00_T1w.nii.gz: no * in the pattern" in line and "quote" in line
    assert not (tmp_path / "m.yaml").exists()


def test_derivatives_and_pipelines_together_still_refused_as_such(tmp_path, capsys):
    """Real derivatives folders with --ants (patterns quoted): the 'not both' message."""
    folder = tmp_path / "deriv"
    folder.mkdir()
    args = ["manifest", str(folder), "--ants", "x/sub-*_", "--images", "img/sub-*.nii.gz"]
    assert main([*args, "--out", str(tmp_path / "m.yaml")]) == 2
    assert "not both" in one_line_error(capsys.readouterr().err, "manifest")


def test_validate_says_which_registration_it_perturbs(tmp_path, capsys):
    """`validate MANIFEST` perturbs the common frame's registration: it says which on the
    terminal, before the run."""
    paths = write_images(tmp_path / "img", 4, labels=True)
    labels = [p.replace(".nii.gz", "_lab.nii.gz") for p in paths]
    ident = []
    for i in range(4):
        ident.append(str(tmp_path / f"id{i}.tfm"))
        sitk.WriteTransform(sitk.AffineTransform(2), ident[-1])
    regs = {
        "first": {"reference": paths[0], "transforms": ident},
        "chosen": {"reference": paths[0], "transforms": ident},
    }
    manifest = tmp_path / "m.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {"images": paths, "labels": labels, "common_frame": "chosen", "registrations": regs}
        )
    )
    out = tmp_path / "val"
    args = ["validate", str(manifest), "--out", str(out), "--displacements", "0,0.5,1"]
    args += ["--repeats", "2", "--samples", "300", "--knots", "6", "--no-progress"]
    assert main(args) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first == f"perturbing registration 'chosen' (the common frame) of {manifest}"
