"""Specificity at a common smoothness: a label-free measure tried for the verdict, NOT KEPT.

Issue 41 (fourth session). Rougher fields fit more of what they should not, so a lower
specificity does not by itself say a registration corresponds better. This measure takes
that advantage away at its source: each registration's displacement fields
``u(p) = T(p) - p`` are convolved with the same isotropic Gaussian of 8 mm on its reference
grid, the images are resampled through ``p + (G * u)(p)`` instead of ``T(p)``, and
specificity is computed as usual (same M, same seed, same frames). Smoothing a linear map
leaves it unchanged, so an affine registration's images are those it already had.

Two rules, each declared in ``bench_verdict.py`` before the cases that check it were judged
(``RULES``), were added to the verdict's evidence here (by wrapping its smoother-fields
step; the package's verdict does not use this measure):

- ``v1``: a preference of at least 1.2x counts where neither registration folds 1% of its
  voxels, the preferred one deforms locally, and the other deforms locally with the preferred
  not rougher by 0.05 in SDlogJ, or the other is affine and the ratio reaches
  ``exp(0.8 SDlogJ(preferred))``. Set on TUNING.
- ``v2``: the same without the affine branch, after HELD_OUT showed it wrong in 3D.

Both decided pairs wrong in 3D on cases that set nothing (``docs/verdict.md``, section
"Specificity at a common smoothness"), so neither is in the verdict: in 3D (3 mm voxels)
8 mm smoothing takes away correspondence that demons got right, and a 25 mm B-spline that
corresponds worse keeps a lower smoothed specificity. In 2D it never decided a pair wrong.

``python benchmarks/bench_common_smoothness.py [--compute]``: ``--compute`` first scores the
smoothed fields of every saved case of the verdict benchmark that lacks them
(``smoothed.json`` in the case's folder, about 10-200 s a case on 2 cores); then every
declared split is judged by today's verdict, and with ``v1`` and ``v2`` added.

The smoothing is done on the registration's reference grid padded by ``4 sigma`` (so the
Gaussian sees the true displacement beyond the edges, not a boundary condition), and the
smoothed field is kept on a grid of spacing ``sigma / 2`` (or the reference's spacing where
that is coarser): a field smoothed at ``sigma`` varies little between nodes ``sigma / 2``
apart.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from itk_nrreval.io._images import Geometry, read_image
from itk_nrreval.io.manifest import Manifest
from itk_nrreval.io.transforms import (
    InMemoryTransform,
    chain_transform,
    displacement_field,
    field_transform,
)

COMMON_SMOOTHNESS_MM = 8.0
"""The Gaussian's standard deviation (mm). 4 mm and 8 mm gave the same decisions on the
tuning split (2D cases only: the 3D ones were not scored at 4 mm)."""


def smoothed_field_transform(
    transform: sitk.Transform, reference: sitk.Image | Geometry, *, sigma_mm: float
) -> sitk.DisplacementFieldTransform:
    """The transform ``p -> p + (G_sigma * u)(p)``, with ``u(p) = T(p) - p``.

    Parameters
    ----------
    transform : sitk.Transform
        T: reference points -> image points (mm, LPS), of any kind (a chain, a field).
    reference : sitk.Image or Geometry
        The registration's reference grid, where ``u`` is smoothed.
    sigma_mm : float
        Standard deviation of the isotropic Gaussian, in mm (physical units, so anisotropic
        voxels and oblique direction cosines are smoothed alike in every direction).

    Returns
    -------
    sitk.DisplacementFieldTransform
        On the reference grid's extent padded by ``4 sigma_mm`` on every side, with spacing
        ``max(sigma_mm / 2, the reference's spacing)`` along each axis and the reference's
        direction cosines; zero displacement outside it.
    """
    if not sigma_mm > 0:
        raise ValueError(f"sigma_mm must be positive, got {sigma_mm!r}")
    g = reference if isinstance(reference, Geometry) else Geometry.from_image(reference)
    padded = _padded(g, 4.0 * sigma_mm, spacing=g.spacing)
    field = displacement_field(transform, padded)
    smooth = [
        sitk.SmoothingRecursiveGaussian(sitk.VectorIndexSelectionCast(field, k), sigma_mm)
        for k in range(field.GetNumberOfComponentsPerPixel())
    ]
    coarse = _padded(g, 4.0 * sigma_mm, spacing=np.maximum(g.spacing, sigma_mm / 2.0))
    resampled = [
        sitk.Resample(c, _image_of(coarse), sitk.Transform(), sitk.sitkLinear, 0.0) for c in smooth
    ]
    return field_transform(sitk.Compose(resampled))


def smoothed_manifest(
    m: Manifest,
    *,
    sigma_mm: float,
    folder: str | os.PathLike,
    frames: Mapping[str, sitk.Transform] | None = None,
) -> Manifest:
    """The manifest of the same images with every registration's fields smoothed alike.

    Parameters
    ----------
    m : Manifest
        A checked manifest.
    sigma_mm : float
        See :func:`smoothed_field_transform`.
    folder : path
        Where the smoothed fields are written (one ``.h5`` transform per registration and
        image; the folder is created).
    frames : dict of str to sitk.Transform, optional
        Each registration's F, common-frame points -> its reference-frame points
        (:attr:`itk_nrreval.io.frame.FrameMapping.transform`), as the unsmoothed registrations
        were brought into the common frame; given, they are kept as the registrations'
        frame transforms (the common registration's is not needed), so that the smoothed
        fields are scored in the same frame rather than one estimated from smoothed fields.

    Returns
    -------
    Manifest
        Labels, per-subject masks and label names dropped (only specificity is asked of
        it); each registration's transforms replaced by its smoothed fields, one per image.
    """
    folder = Path(folder)
    registrations = {}
    for k, (name, r) in enumerate(m.registrations.items()):
        reference = Geometry.from_image(read_image(r.reference, what="reference"))
        chains = []
        for i, chain in enumerate(r.transforms):
            path = folder / f"{k:03d}" / f"{i:05d}.h5"
            path.parent.mkdir(parents=True, exist_ok=True)
            smoothed = smoothed_field_transform(
                chain_transform(chain), reference, sigma_mm=sigma_mm
            )
            sitk.WriteTransform(smoothed, str(path))
            chains.append((path,))
        frame = r.frame_transform
        if frames is not None and name != m.common_frame:
            frame = InMemoryTransform.from_object(frames[name], name=f"{name} frame")
        registrations[name] = dataclasses.replace(
            r, transforms=tuple(chains), frame_transform=frame
        )
    return dataclasses.replace(
        m, labels=None, masks=None, label_names=None, registrations=registrations
    )


def _padded(g: Geometry, margin_mm: float, *, spacing) -> Geometry:
    """`g`'s extent grown by `margin_mm` on every side, sampled at `spacing` (mm)."""
    spacing = np.asarray(spacing, dtype=float)
    direction = np.asarray(g.direction, dtype=float).reshape(g.dimension, g.dimension)
    lengths = (np.asarray(g.size) - 1) * np.asarray(g.spacing) + 2.0 * margin_mm
    size = np.floor(lengths / spacing + 1e-9).astype(int) + 1
    # centred on g's centre: the same physical box whatever the spacing
    centre = np.asarray(g.origin) + direction @ ((np.asarray(g.size) - 1) * g.spacing / 2.0)
    origin = centre - direction @ ((size - 1) * spacing / 2.0)
    return Geometry(
        size=tuple(int(s) for s in size),
        spacing=tuple(float(s) for s in spacing),
        origin=tuple(float(o) for o in origin),
        direction=tuple(float(d) for d in direction.ravel()),
    )


def _image_of(g: Geometry) -> sitk.Image:
    """An empty image on grid `g` (a resampling target)."""
    return g.apply_to(sitk.Image([int(s) for s in g.size], sitk.sitkFloat64))


# ------------------------------------------------------------------ the verdict benchmark

HERE = Path(__file__).resolve().parent
SMOOTHED_JSON = "smoothed.json"
RULES = ("v1", "v2")
_MEASURE = "smoothed_specificity"


def _verdict_bench():
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("bench_verdict", HERE / "bench_verdict.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("bench_verdict", module)
    spec.loader.exec_module(module)
    return module


def add_smoothed(bv, case: str) -> None:
    """Score a saved case's registrations with their fields smoothed (frames kept, the
    case's M and seed) into the case's ``smoothed.json``; nothing is registered again."""
    import tempfile
    import time

    import itk_nrreval as nr
    from itk_nrreval.io.manifest import load_manifest

    evaluation = bv._load(case)
    m = bv._quiet(load_manifest, bv.manifest_of(case))
    frames = {name: s.frame.transform for name, s in evaluation.scores.items()}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        smoothed = smoothed_manifest(m, sigma_mm=COMMON_SMOOTHNESS_MM, folder=folder, frames=frames)
        result = bv._quiet(
            nr.evaluate,
            smoothed,
            n_samples=bv.N_SAMPLES,
            seed=bv.SEED,
            confidence=False,
            inverse_consistency=False,
            progress=False,
        )
    values = {n: [s.specificity.value, s.specificity.stderr] for n, s in result.scores.items()}
    record = {"sigma_mm": COMMON_SMOOTHNESS_MM, "specificity": values}
    record["seconds"] = round(time.perf_counter() - t0, 1)
    (bv.OUT / case / SMOOTHED_JSON).write_text(json.dumps(record, indent=1) + "\n")
    print(f"[common smoothness] {case}: {record['seconds']:.0f} s", flush=True)


def _smoothed_preference(rule, a, b, smoothed, rough, folded, deforms):
    """The registration the rule lets specificity at a common smoothness prefer, with the
    log ratio, or None (module docstring)."""
    import math

    p, q = (a, b) if smoothed[a] < smoothed[b] else (b, a)
    gain = math.log(smoothed[q] / smoothed[p])
    if gain < math.log(1.2) or not deforms[p] or max(folded[p], folded[q]) >= 0.01:
        return None
    if deforms[q]:
        return (p, gain) if rough[p] - rough[q] < 0.05 else None
    if rule == "v1" and gain >= 0.8 * rough[p]:
        return p, gain
    return None


@contextlib.contextmanager
def _with_rule(rule: str | None, smoothed: Mapping[str, float] | None):
    """The package's verdict with the rule's evidence added to every pair that has
    subject-level confidence (its smoother-fields step wrapped); None: as it is."""
    from itk_nrreval.measures import _pair_evidence as e
    from itk_nrreval.measures import verdict as v

    if rule is None or smoothed is None:
        yield
        return
    original = v.add_smoother_evidence

    def add(evidence, c, facts):
        original(evidence, c, facts)
        if c is None:
            return
        found = _smoothed_preference(
            rule, c.a, c.b, smoothed, facts.rough, facts.folded, facts.deforms
        )
        if found is not None:
            p, gain = found
            evidence[_MEASURE] = e.Preference(p, c.b if p == c.a else c.a, gain, None)

    v.add_smoother_evidence = add  # the name verdict calls it by
    e.WORD[_MEASURE] = "specificity at a common smoothness"
    try:
        yield
    finally:
        v.add_smoother_evidence = original
        e.WORD.pop(_MEASURE)


def main(argv: list[str] | None = None) -> dict:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--compute", action="store_true", help="score cases that lack it")
    args = parser.parse_args([] if argv is None else argv)
    bv = _verdict_bench()
    declared = {c: bv.split_of(c) for c in bv._cases() if (bv.OUT / c / "truth.json").exists()}
    if args.compute:
        for case in declared:
            if not (bv.OUT / case / SMOOTHED_JSON).exists():
                add_smoothed(bv, case)
    table: dict = {}
    for case, split in declared.items():
        path = bv.OUT / case / SMOOTHED_JSON
        if not path.exists():
            continue
        values = {k: v[0] for k, v in json.loads(path.read_text())["specificity"].items()}
        second = case.startswith("unseen_")
        for labels in (False, True):
            mode = ("second scan, " if second else "") + ("with" if labels else "without")
            mode += " labels"
            for rule in (None, *RULES):
                with _with_rule(rule, values):
                    rows = bv.judge(case, labels=labels)
                key = (split, mode, rule or "today")
                cell = table.setdefault(key, {"right": 0, "wrong": 0, "open": 0, "wrong_pairs": []})
                counts = bv._counts(rows)  # near-ties are counted apart there, and left out here
                for k in ("right", "wrong", "open"):
                    cell[k] += counts[k]
                cell["wrong_pairs"] += [
                    f"{case}: decided {r['decision']}; true errors {r['a']} "
                    f"{r['true_error_a_mm']:.2f} mm, {r['b']} {r['true_error_b_mm']:.2f} mm"
                    for r in rows
                    if r["outcome"] == "wrong"
                ]
    lines = ["| split | mode | today | v1 | v2 |", "|---|---|--:|--:|--:|"]
    for split, mode in dict.fromkeys((s, m) for s, m, _ in table):
        cells = [table[(split, mode, r)] for r in ("today", *RULES)]
        lines.append(
            f"| {split} | {mode} | "
            + " | ".join(f"{c['right']} / {c['wrong']} / {c['open']}" for c in cells)
            + " |"
        )
    print("\n".join(lines))
    for key, cell in table.items():
        for pair in cell["wrong_pairs"]:
            print(f"- wrong, {key[2]}, {key[1]}: {pair}")
    return {" / ".join(k): {n: c[n] for n in ("right", "wrong", "open")} for k, c in table.items()}


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
