"""Evaluate registrations held in memory, from a Python console -- written for 3D Slicer.

In the 3D Slicer Python console (View > Python Interactor), with the training volumes, each
registration's reference volume and its transform nodes loaded in the scene, edit the node
names in ``SLICER_SCENE`` below, then::

    exec(open("/path/to/itk-nrreval/examples/slicer_console.py").read())

(``itk-nrreval`` must be installed in Slicer's Python: ``slicer.util.pip_install(...)``.)
Volume nodes become SimpleITK images with Slicer's ``sitkUtils.PullVolumeFromSlicer``,
transform nodes SimpleITK transforms (each saved to a temporary ``.h5`` with
``slicer.util.saveNode`` and read back), nothing is written to a manifest, the evaluation runs
on the objects (:func:`itk_nrreval.evaluate` takes them wherever it takes a path), and the
verdict comes back in a message box and in the console.

Outside Slicer, ``python examples/slicer_console.py`` runs the same evaluation on a generated
population held in memory (a 2D phantom: 6 subjects with their true transforms, and a
registration that gets only each subject's pose right), so that everything but the Slicer
lines is tested. The Slicer-only lines are the functions marked "Slicer only", called only
when ``IN_SLICER`` is true.

Conventions: SimpleITK images from ``sitkUtils`` are in ITK's physical space (mm, LPS; Slicer
shows RAS). A transform node saved to a file is written in ITK's *resampling* convention --
reference (fixed) points to moving points -- the convention of the toolkit, for the node that
moves a training volume onto the registration's reference (what BRAINSFit, Elastix and ANTs
registrations in Slicer output). A non-linear transform that Slicer can only write in the
opposite direction is written as an ``Inverse...`` ITK type (Slicer's developer guide,
"Transform files"), which SimpleITK cannot read: the error below says so; invert it in
Slicer's Transforms module (or export the registration's transform as a displacement field)
first.

Every file this script writes goes to a temporary folder, removed at the end (set ``OUT`` to
keep the reports).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

import SimpleITK as sitk

import itk_nrreval as nr

#: True inside 3D Slicer's Python: then the scene's nodes are evaluated.
IN_SLICER = "slicer" in sys.modules

#: Slicer only: the node names of the scene (edit). One transform node per training volume,
#: per registration (or a list of nodes: a chain in ANTs order, the first acting first).
SLICER_SCENE = {
    "images": ["subject01", "subject02", "subject03", "subject04", "subject05", "subject06"],
    "labels": None,  # or the label-map volume nodes, one per training volume
    "registrations": {
        "elastix": {
            "reference": "template",
            "transforms": ["T01", "T02", "T03", "T04", "T05", "T06"],
        },
    },
}

#: Folder to keep the reports in (None: a temporary folder, removed at the end).
OUT: str | None = None


# ----------------------------------------------------------------------------- Slicer only


def volume_from_slicer(name: str) -> sitk.Image:
    """Slicer only: a volume node as a SimpleITK image (LPS geometry, voxels copied)."""
    import sitkUtils  # Slicer's module

    return sitkUtils.PullVolumeFromSlicer(name)


def transform_from_slicer(name: str, folder: str) -> sitk.Transform:
    """Slicer only: a transform node as a SimpleITK transform (via a temporary .h5 file)."""
    import slicer  # Slicer's module

    node = slicer.util.getNode(name)
    path = os.path.join(folder, f"{node.GetID()}.h5")
    if not slicer.util.saveNode(node, path):
        raise RuntimeError(f"transform node {name!r}: Slicer could not save it")
    try:
        return sitk.ReadTransform(path)  # in memory now; the file goes with `folder`
    except RuntimeError as exc:
        raise RuntimeError(
            f"transform node {name!r}: SimpleITK cannot read it ({str(exc).splitlines()[-1]}); "
            "a non-linear transform Slicer writes as an Inverse... ITK type cannot be read: "
            "invert it in the Transforms module, or export it as a displacement field"
        ) from None


def scene_from_slicer(folder: str) -> dict:
    """Slicer only: the manifest of SLICER_SCENE, with volumes and transforms in memory."""

    def chain(item):
        if isinstance(item, (list, tuple)):
            return [transform_from_slicer(n, folder) for n in item]
        return transform_from_slicer(item, folder)

    scene = SLICER_SCENE
    manifest = {"images": [volume_from_slicer(n) for n in scene["images"]]}
    if scene.get("labels"):
        manifest["labels"] = [volume_from_slicer(n) for n in scene["labels"]]
    manifest["registrations"] = {}
    for reg, entry in scene["registrations"].items():
        converted = {
            **entry,  # reference_index as it is
            "reference": volume_from_slicer(entry["reference"]),
            "transforms": [chain(t) for t in entry["transforms"]],
        }
        if entry.get("frame_transform"):
            converted["frame_transform"] = chain(entry["frame_transform"])
        manifest["registrations"][reg] = converted
    return manifest


def show_in_slicer(text: str) -> None:
    """Slicer only: the verdict in a message box (it is also printed to the console)."""
    import slicer  # Slicer's module

    slicer.util.infoDisplay(text, windowTitle="itk-nrreval: which registration is best")


# ----------------------------------------------------------------------------- anywhere


def generated_scene() -> dict:
    """What the scene would hold, generated: a manifest of in-memory SimpleITK objects.

    Six 2D phantom subjects (``data_synth``), their label maps, and two registrations to the
    template: ``truth`` (each subject's true transform, a pose and a displacement field) and
    ``pose_only`` (the pose alone, no non-rigid part).
    """
    from data_synth import make_population

    population = make_population("phantom", dim=2, n=6, seed=1, size=64, spacing=2.0)
    subjects = population.subjects
    return {
        "images": [s.image for s in subjects],
        "labels": [s.labels for s in subjects],
        "registrations": {
            "truth": {
                "reference": population.template,
                "transforms": [s.template_to_subject for s in subjects],  # template -> subject
            },
            "pose_only": {
                "reference": population.template,
                # template_to_subject is CompositeTransform([pose, field]): pose(field(p))
                "transforms": [s.template_to_subject.GetNthTransform(0) for s in subjects],
            },
        },
    }


def main(argv: list[str] | None = None) -> nr.EvaluationResult:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=20_000, metavar="M")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    # not examples/_output.py: in Slicer this file is exec'd without its folder on sys.path
    parser.add_argument("--out", metavar="DIR", help="keep the reports in DIR (default: removed)")
    args = parser.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="nrreval-console-") as tmp:
        manifest = scene_from_slicer(tmp) if IN_SLICER else generated_scene()
        out = args.out or OUT or os.path.join(tmp, "reports")
        result = nr.evaluate(manifest, n_samples=args.samples, progress=not args.quiet)
        result.write(out)  # the reports `nrreval evaluate` writes
        lines = [*result.verdict.text, ""]
        lines += [
            f"{name}: specificity {s.specificity.value:.4g}"
            + (f", overlap (inverse volume) {s.overlap['inverse_volume']:.3f}" if s.overlap else "")
            + (f"  [flagged: {'; '.join(s.flags)}]" if s.flags else "")
            for name, s in ((n, result.scores[n]) for n in result.verdict.ranking)
        ]
        text = "\n".join(lines)
        print(text)
        kept = args.out or OUT
        print(f"reports: {out}" + ("" if kept else " (temporary: --out DIR or OUT keeps them)"))
        if IN_SLICER:
            show_in_slicer(text)
    return result


if __name__ == "__main__":
    main([] if IN_SLICER else None)  # Slicer's own command line is not this script's
