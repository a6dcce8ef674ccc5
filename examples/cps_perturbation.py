"""Perturb a registered brain-like image with a random clamped-plate-spline warp (paper, Fig. 1).

Draws a warp of mean displacement d = 3 pixels on a 141 x 141 generated slice, checks that it
is a diffeomorphism, warps the image and its labels the paper's way (I~(psi(p)) = I(p)), and
does the same with SimpleITK's resampler to show the two agree. Saves a figure.

    python examples/cps_perturbation.py [--out DIR]   # DIR/cps_perturbation.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from _output import add_out_option, output_folder

import itk_nrreval as nr
from data_synth import perfectly_registered_arrays


def draw(out: Path) -> None:
    images, labels = perfectly_registered_arrays("phantom", n=1, seed=0)
    image, label = images[0], labels[0]

    warp = nr.random_cps(image.shape, 3.0, n_knots=25, seed=1)
    field = warp.field()  # psi(p) - p, pixels, (y, x, [dx, dy])
    print(f"mean displacement {np.linalg.norm(field, axis=-1).mean():.12f} px")
    print(f"max displacement {np.linalg.norm(field, axis=-1).max():.2f} px")
    print(f"min Jacobian determinant {warp.min_jacobian:.3f}")
    print(f"this warp's shape stays diffeomorphic up to d = {nr.max_safe_displacement(field):.2f}")

    warped, members = nr.warp_stack(image[None], [warp], labels=label[None])

    # the same with SimpleITK: resample through the inverse field (output -> input points)
    inv = nr.cps_warp(image.shape, 3.0, n_knots=25, seed=1, inverse=True)
    tx = sitk.DisplacementFieldTransform(sitk.Image(inv))  # it takes over its input: a copy
    img = sitk.GetImageFromArray(image)
    via_itk = sitk.GetArrayFromImage(sitk.Resample(img, img, tx, sitk.sitkLinear))
    print(f"numpy vs SimpleITK resampling, max difference {np.abs(via_itk - warped[0]).max():.2e}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(12, 4.2))
    ax[0].imshow(image, cmap="gray")
    ax[0].contour(label, levels=np.arange(label.max()) + 0.5, linewidths=0.5, cmap="tab20")
    ax[0].set_title("registered image and labels")
    ax[1].imshow(image, cmap="gray")
    c, r = (np.array(image.shape) - 1) / 2, min(image.shape) / 2
    ax[1].add_patch(plt.Circle((c[1], c[0]), r, fill=False, color="g"))
    knots = warp.spline.knots * r + c[::-1]
    moves = warp.displacement(knots)
    ax[1].plot(knots[:, 0], knots[:, 1], "r.")
    ax[1].quiver(knots[:, 0], knots[:, 1], moves[:, 0], moves[:, 1], color="y",
                 angles="xy", scale_units="xy", scale=0.3)  # fmt: skip
    ax[1].set_title("bounding circle, knots, knot displacements")
    ax[2].imshow(warped[0], cmap="gray")
    ax[2].contour(members[0].argmax(0), levels=np.arange(label.max()) + 0.5, linewidths=0.5,
                  cmap="tab20")  # fmt: skip
    ax[2].set_title("warped, d = 3.0 pixels")
    for a in ax:
        a.set_axis_off()
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(f"wrote {out}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_out_option(parser)
    args = parser.parse_args()
    with output_folder(args.out, prefix="nrreval-cps-") as folder:
        draw(folder / "cps_perturbation.png")


if __name__ == "__main__":
    main()
