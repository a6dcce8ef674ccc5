"""Write the NiftyReg fixtures of tests/test_foreign_transforms.py with NiftyReg's own tools.

The files here are NiftyReg's output, kept so that the tests compare the toolkit's reading of
NiftyReg's formats with NiftyReg itself without installing it (it has no wheel: the PyPI
sdist ``niftyreg`` 1.5.70rc1 builds its command-line tools with CMake and a C++ compiler,
``CMAKE_POLICY_VERSION_MINIMUM=3.5 pip wheel niftyreg`` with CMake 4, about four minutes).

    python tests/data/niftyreg/make_fixtures.py /path/to/niftyreg/bin

For each of 2D and 3D: a reference and a floating image on oblique, anisotropic grids some
60 mm apart (SimpleITK writes them; 3D reference with a negative-determinant grid), then

- ``aff{d}.txt``: ``reg_transform -makeAff`` (NiftyReg's affine text, as reg_aladin writes it);
- ``cpp{d}.nii.gz``: ``reg_f3d`` (a few iterations from that affine): a control-point grid;
- ``def{d}.nii.gz`` / ``disp{d}.nii.gz``: ``reg_transform -def`` / ``-disp`` of the grid;
- ``affdef{d}.nii.gz``: ``reg_transform -def`` of the affine (its mapping of every voxel);
- ``land{d}.txt``: world points (mm, RAS; off the voxel centres, inside the reference);
- ``land{d}_aff.txt`` / ``land{d}_cpp.txt``: ``reg_transform -land`` of them through the affine
  and through the control-point grid (NiftyReg's own mapping of the points; it prints six
  significant digits, so every coordinate is kept below 100 mm: 5e-5 mm).
"""

import subprocess
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk

HERE = Path(__file__).resolve().parent


def blobs(size, spacing, origin, direction, shift):
    """Smooth blobs (something for reg_f3d to align) on the given grid."""
    img = sitk.Image([int(s) for s in size], sitk.sitkFloat32)
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    img.SetDirection(direction)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in size], indexing="ij"), -1).reshape(
        -1, len(size)
    )
    pts = np.array(
        [img.TransformContinuousIndexToPhysicalPoint(p.tolist()) for p in idx.astype(float)]
    )
    centre = np.array(
        img.TransformContinuousIndexToPhysicalPoint(((np.array(size) - 1) / 2).tolist())
    )
    d = pts - centre - shift
    values = np.exp(-(d**2).sum(1) / 60.0) + 0.5 * np.exp(-((d - 4) ** 2).sum(1) / 20.0)
    arr = values.reshape(size).transpose(*range(len(size))[::-1]).astype(np.float32)
    out = sitk.GetImageFromArray(arr)
    out.CopyInformation(img)
    return out


def rotation(dim, angles):
    if dim == 2:
        c, s = np.cos(angles[0]), np.sin(angles[0])
        return (c, -s, s, c)
    t = sitk.Euler3DTransform()
    t.SetRotation(*angles)
    return t.GetMatrix()


def run(bin_dir, *args):
    subprocess.run(
        [str(Path(bin_dir) / args[0]), *map(str, args[1:])],
        check=True,
        cwd=HERE,
        stdout=subprocess.DEVNULL,
    )


def centred(size, spacing, centre_lps, direction):
    """The origin that puts a grid's centre at `centre_lps`."""
    m = np.array(direction).reshape(len(size), len(size)) * np.array(spacing)
    return (np.array(centre_lps) - m @ ((np.array(size) - 1) / 2)).tolist()


def main(bin_dir):
    for dim in (2, 3):
        lps = np.r_[-1.0, -1.0, 1.0][:dim]
        if dim == 3:
            ref_dir = np.array(rotation(3, (0.2, -0.1, 0.3))).reshape(3, 3) @ np.diag([1, 1, -1])
            ref_grid = ((16, 14, 12), (1.2, 0.9, 1.5), ref_dir.ravel().tolist())
            flo_grid = ((18, 13, 11), (0.8, 1.1, 1.3), rotation(3, (-0.3, 0.25, 0.1)))
            ref_centre = np.array([-20.0, 30.0, 10.0])
            aff = (0.05, -0.03, 0.08, 50.0, -45.0, 40.0, 1.05, 0.95, 1.02, 0.02, -0.01, 0.03)
        else:
            ref_grid = ((20, 16), (1.2, 0.9), rotation(2, (0.3,)))
            flo_grid = ((22, 15), (0.8, 1.1), rotation(2, (-0.25,)))
            ref_centre = np.array([-20.0, 30.0])
            aff = (0.0, 0.0, 0.15, 50.0, -45.0, 0.0, 1.05, 0.95, 1.0, 0.03, 0.0, 0.0)
        run(bin_dir, "reg_transform", "-makeAff", *aff, f"aff{dim}.txt")
        m = np.loadtxt(HERE / f"aff{dim}.txt")  # reference world -> floating world (RAS)
        centre_ras = np.r_[ref_centre * lps, np.zeros(3 - dim), 1.0]
        flo_centre = (m @ centre_ras)[:dim] * lps  # where the affine takes it, LPS
        size, spacing, direction = ref_grid
        ref = blobs(size, spacing, centred(size, spacing, ref_centre, direction), direction, 0)
        size, spacing, direction = flo_grid
        flo = blobs(size, spacing, centred(size, spacing, flo_centre, direction), direction, 2.5)
        sitk.WriteImage(ref, str(HERE / f"ref{dim}.nii.gz"))
        sitk.WriteImage(flo, str(HERE / f"flo{dim}.nii.gz"))
        run(
            bin_dir,
            "reg_f3d",
            "-ref",
            f"ref{dim}.nii.gz",
            "-flo",
            f"flo{dim}.nii.gz",
            "-aff",
            f"aff{dim}.txt",
            "-cpp",
            f"cpp{dim}.nii.gz",
            "-res",
            "/dev/null",
            "-sx",
            "4",
            "-ln",
            "1",
            "-maxit",
            "300",
            "-be",
            "0.0001",
        )
        run(
            bin_dir,
            "reg_transform",
            "-ref",
            f"ref{dim}.nii.gz",
            "-def",
            f"cpp{dim}.nii.gz",
            f"def{dim}.nii.gz",
        )
        run(
            bin_dir,
            "reg_transform",
            "-ref",
            f"ref{dim}.nii.gz",
            "-disp",
            f"cpp{dim}.nii.gz",
            f"disp{dim}.nii.gz",
        )
        run(
            bin_dir,
            "reg_transform",
            "-ref",
            f"ref{dim}.nii.gz",
            "-def",
            f"aff{dim}.txt",
            f"affdef{dim}.nii.gz",
        )
        # world points (RAS) at fractional voxel positions well inside the reference
        rng = np.random.default_rng(dim)
        idx = rng.uniform(1.5, np.array(ref.GetSize()) - 2.5, (12, dim))
        pts = np.array([ref.TransformContinuousIndexToPhysicalPoint(p.tolist()) for p in idx])
        np.savetxt(HERE / f"land{dim}.txt", pts * lps, fmt="%.6f")
        run(
            bin_dir,
            "reg_transform",
            "-ref",
            f"ref{dim}.nii.gz",
            "-land",
            f"aff{dim}.txt",
            f"land{dim}.txt",
            f"land{dim}_aff.txt",
        )
        run(
            bin_dir,
            "reg_transform",
            "-ref",
            f"ref{dim}.nii.gz",
            "-land",
            f"cpp{dim}.nii.gz",
            f"land{dim}.txt",
            f"land{dim}_cpp.txt",
        )


if __name__ == "__main__":
    main(sys.argv[1])
