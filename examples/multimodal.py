"""Two ways of registering a group of T1- and T2-weighted images, compared (paper, Section VI).

Run: ``python examples/multimodal.py [--out DIR]`` (one to two minutes on 2 cores; by default
everything is written into a temporary folder and removed; with ``--out DIR`` the population,
its manifest and the three registrations are kept there, ready for ``nrreval evaluate``).

A small two-modality population is generated with known true correspondence (every subject
imaged in a T1-like and a T2-like contrast of the same anatomy, :mod:`data_synth`), and
registered two ways with :func:`itk_nrreval.experiments.registration.register_multimodal`:

* ``joint``: every image, T1 and T2, to one T1 reference with mutual information (affine,
  then B-spline);
* ``per-group``: the T1 images to a T1 reference and the T2 images to a T2 reference, each with
  a same-contrast metric, and one mutual-information registration linking the T2 reference to
  the T1 reference, composed into every T2 image's transform;
* ``affine``: the affine stage of ``joint`` alone, the control.

Each is one registration of all N images in one frame, added to the population's manifest
(which lists each image's modality under ``groups`` and the true transforms as ``truth``).
:func:`itk_nrreval.evaluate` scores them in one common frame with the specificity of a
Gaussian mixture (one Gaussian per modality), and
:func:`itk_nrreval.experiments.correspondence.correspondence_error` gives the true mean
correspondence error. The last column is the part of that error the mixture cannot see: the distance
between the T1 images' and the T2 images' mean correspondence (each Gaussian of the mixture sits
around its own modality's mean, so moving all T2 images together changes nothing in it).
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np
import SimpleITK as sitk
from _output import add_out_option, output_folder

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval.experiments.correspondence import correspondence_error
from itk_nrreval.experiments.registration import ElastixWorker, register_multimodal
from itk_nrreval.io.frame import read_chains, resampling_transform
from itk_nrreval.io.manifest import load_manifest
from itk_nrreval.io.transforms import displacement_field

N_SUBJECTS = 5
CONTRASTS = ("t1", "t2")
RUNS = {
    "joint": {"strategy": "joint"},
    "per-group": {"strategy": "per-group"},
    "affine": {"strategy": "joint", "deformable": False},
}


def _stem(path: str) -> str:
    return Path(path).name.removesuffix(".nii.gz")


def main(folder: Path, *, n: int = N_SUBJECTS, n_samples: int = 20_000) -> dict:
    """Generate, register, evaluate in `folder`; print the table and return the numbers."""
    pop = make_population("phantom", dim=2, n=n, seed=0, spacing=2.8, size=80, contrasts=CONTRASTS)
    manifest = write_population(pop, folder, montage=False, progress=False)
    m = load_manifest(manifest)
    images = [str(p) for p in m.images]
    names = [_stem(p) for p in images]
    with ElastixWorker() as worker:  # one elastix start-up for every registration
        for name, kwargs in RUNS.items():
            result = register_multimodal(
                images, m.groups, **kwargs, seed=0, progress=False, elastix_worker=worker
            )
            result.add_to_manifest(manifest, name, out=folder / name, names=names)
            print(f"registered {name:10s} in {result.seconds:5.1f} s", flush=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # groups: intervals are Monte-Carlo only
        evaluation = nr.evaluate(manifest, n_samples=n_samples, confidence=False, progress=False)
    # The common frame is `truth` (the template): average the error over the head.
    head = sitk.GetArrayFromImage(pop.template_labels) > 0
    truth = [s.subject_to_template for c in CONTRASTS for s in pop.subjects]
    error = correspondence_error(evaluation, manifest, truth, mask=head)
    gap = _modality_gap(evaluation, manifest, truth, pop.template, head)
    rows = {}
    for name, scores in evaluation.scores.items():
        spec = scores.specificity
        mix = spec.mixture
        rows[name] = {
            "specificity": spec.value,
            "stderr": spec.stderr,
            "per_group": dict(zip(mix.groups, map(float, mix.values), strict=True)),
            "nearest_counts": mix.nearest_counts.tolist(),
            "true_error_mm": error[name],
            "t1_t2_gap_mm": gap[name],
        }
    print(_table(rows, list(mix.groups)))
    return rows


def _modality_gap(evaluation, manifest, truth, grid: sitk.Image, mask) -> dict[str, float]:
    """Per registration: mean over the head of ``|mean_T1 y_i - mean_T2 y_i|`` (mm).

    ``y_i(p)`` is the template point that image i's correspondence of common point p truly
    is (as in :func:`~itk_nrreval.experiments.correspondence.correspondence_error`).
    """
    m = load_manifest(manifest)
    groups = np.asarray(m.groups)
    out = {}
    for name, scores in evaluation.scores.items():
        y = np.stack(
            [
                sitk.GetArrayFromImage(
                    displacement_field(
                        sitk.CompositeTransform(
                            [s, resampling_transform(t, scores.frame.transform)]
                        ),
                        grid,
                    )
                )[mask]
                for t, s in zip(read_chains(m, name), truth, strict=True)
            ]
        )
        means = [y[groups == g].mean(axis=0) for g in CONTRASTS]
        out[name] = float(np.linalg.norm(means[0] - means[1], axis=-1).mean())
    return out


def _table(rows: dict, groups: list) -> str:
    head = ["registration", "mixture specificity", "s.e."]
    head += [f"{g} part" for g in groups]
    head += ["samples nearest the other modality", "true corr. error (mm)", "T1-T2 gap (mm)"]
    lines = ["| " + " | ".join(head) + " |", "|---" + "|--:" * (len(head) - 1) + "|"]
    for name, r in rows.items():
        counts = np.asarray(r["nearest_counts"])
        across = counts.sum() - np.trace(counts)
        cells = [name, f"{r['specificity']:.4g}", f"{r['stderr']:.2g}"]
        cells += [f"{r['per_group'][g]:.4g}" for g in groups]
        cells += [f"{across} / {counts.sum()}", f"{r['true_error_mm']:.2f}"]
        cells += [f"{r['t1_t2_gap_mm']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_out_option(parser)
    with output_folder(parser.parse_args().out, prefix="nrreval-multimodal-") as folder:
        main(folder)
