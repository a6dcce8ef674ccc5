"""Register a small synthetic group with the paper's five algorithms and write a manifest.

Run: ``python examples/register_a_group.py [--out DIR]`` (default: a temporary folder,
removed). Each registration goes to ``DIR/<name>/`` (per-image ``.h5`` transforms
reference -> image, the reference image, ``registration.json``) and is added to
``DIR/manifest.yaml``, ready for ``nrreval evaluate``. One elastix worker serves both
pairwise registrations.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from _output import add_out_option, output_folder

from itk_nrreval import register
from itk_nrreval.experiments.registration._elastix_worker import ElastixWorker
from itk_nrreval.io.manifest import add_registration


def blobs(n_images: int = 8, size: int = 96, seed: int = 0) -> list[sitk.Image]:
    """Smooth ellipse phantoms with random affine pose and shape (a stand-in for real data)."""
    rng = np.random.default_rng(seed)
    yy, xx = (np.mgrid[:size, :size] + 0.5) / size - 0.5
    out = []
    for _ in range(n_images):
        a, b = rng.uniform(0.3, 0.42, 2)
        cx, cy = rng.uniform(-0.05, 0.05, 2)
        img = (((xx - cx) / a) ** 2 + ((yy - cy) / b) ** 2 <= 1).astype(np.float32)
        img[((xx - cx) / (0.5 * a)) ** 2 + ((yy - cy - 0.05) / (0.4 * b)) ** 2 <= 1] = 0.4
        out.append(sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(img), 1.0))
    return out


def main(out: Path) -> None:
    images = blobs()
    paths = []
    for i, img in enumerate(images):
        paths.append(out / "images" / f"s{i:02d}.nii.gz")
        paths[-1].parent.mkdir(parents=True, exist_ok=True)
        sitk.WriteImage(img, str(paths[-1]))
    runs = [
        ("fluid", {"method": "fluid"}),
        ("groupwise", {"method": "groupwise"}),
        ("pairwise-near-mean", {"method": "pairwise", "reference_choice": "near-mean"}),
        ("pairwise-far-from-mean", {"method": "pairwise", "reference_choice": "far-from-mean"}),
        ("affine", {"method": "affine"}),
    ]
    with ElastixWorker() as worker:
        for name, kwargs in runs:
            extra = {"elastix_worker": worker} if kwargs["method"] == "pairwise" else {}
            result = register(paths, **kwargs, **extra)
            written = result.write(out / name, names=[p.name.split(".")[0] for p in paths])
            add_registration(
                out / "manifest.yaml",
                name,
                reference=written["reference"],
                transforms=written["transforms"],
                reference_index=result.reference_index,
                images=paths,
            )
            print(f"{name:24s} {result.engine:9s} {result.seconds:6.1f} s")
    print(f"manifest: {out / 'manifest.yaml'}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_out_option(parser)
    with output_folder(parser.parse_args().out, prefix="nrreval-register-") as folder:
        main(folder)
