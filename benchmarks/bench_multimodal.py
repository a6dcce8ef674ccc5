"""Multi-modal groups: two registration strategies ranked by mixture specificity and by the truth.

For a phantom and an MNI-based 2D population of ``N_SUBJECTS`` subjects, each imaged in a
T1-like and a T2-like contrast (:mod:`data_synth`, known true correspondence), the group of
2 x N_SUBJECTS images is registered with
:func:`itk_nrreval.experiments.registration.register_multimodal`:

* ``joint``: every image to one T1 reference, mutual information (affine, B-spline);
* ``per-group``: each modality to its own reference with normalised correlation, and one
  mutual-information registration linking the T2 reference to the T1 reference;
* ``joint-affine`` / ``per-group-affine``: their affine stages alone (controls);
* ``per-group-link-2mm``: ``per-group`` with an error of ``LINK_ERROR_MM`` put into its link
  (every T2 transform ``T_j o L`` becomes ``T_j o L o D``, D a translation of the reference
  frame): the T2 images move together, away from the T1 images, by a known amount.

All are evaluated with the true transforms (``truth``) in one manifest, whose common frame is
the template. Reported per registration: the specificity of the Gaussian mixture (one
Gaussian per modality; value, Monte-Carlo standard error, the T1 and T2 parts, and how many
of the samples of each modality land nearest an image of the other), the specificity of one
Gaussian over all images (groups ignored), and the true mean correspondence error over the
head (:func:`itk_nrreval.experiments.correspondence.correspondence_error`) split into the spread
within each modality and the distance between the two modalities' mean correspondences (the part a
shared link error makes, and which the mixture -- one Gaussian per modality, each around its
own mean -- cannot see; the ``per-group-link-2mm`` row measures how little it sees).

Writes ``docs/multimodal_benchmark.png`` (mixture specificity against the true error).

Run: ``python benchmarks/run_all.py multimodal`` (about 10 minutes on 2 cores;
``MULTIMODAL_QUICK=1``: 4 subjects on a coarse grid, the phantom only).
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval.experiments.correspondence import correspondence_error
from itk_nrreval.experiments.registration import ElastixWorker, register_multimodal
from itk_nrreval.io.frame import read_chains, resampling_transform
from itk_nrreval.io.manifest import load_manifest
from itk_nrreval.io.transforms import displacement_field, flatten

QUICK = os.environ.get("MULTIMODAL_QUICK") == "1"
N_SUBJECTS = 4 if QUICK else 12
CONTRASTS = ("t1", "t2")
KINDS = ("phantom",) if QUICK else ("phantom", "mni")
GRID = {"spacing": 2.8, "size": 80} if QUICK else {}
N_SAMPLES = 20_000 if QUICK else 100_000
#: The error put into the per-group link (mm, along x): about three times the link's own.
LINK_ERROR_MM = 2.0
SEED = 0
RUNS = {
    "joint": {"strategy": "joint"},
    "per-group": {"strategy": "per-group"},
    "joint-affine": {"strategy": "joint", "deformable": False},
    "per-group-affine": {"strategy": "per-group", "deformable": False},
}


def _stem(path) -> str:
    return Path(path).name.removesuffix(".nii.gz")


def _evaluate(manifest, cache: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # groups: Monte-Carlo error only
        return nr.evaluate(
            manifest,
            n_samples=N_SAMPLES,
            seed=SEED,
            confidence=False,
            progress=False,
            execution=nr.Execution(cache=cache),
        )


def _error_parts(evaluation, manifest, truth, template, mask, groups) -> dict[str, dict]:
    """Per registration: the true error split into within-group spread and between-group gap.

    ``y_i(p)`` is the template point that image i's correspondence of common point p truly
    is. Within group g: the mean of ``|y_i - mean_{j in g} y_j|`` over i in g and p; between:
    the mean over p of ``|mean_{t1} y - mean_{t2} y|``.
    """
    m = load_manifest(manifest)
    groups = np.asarray(groups)
    out = {}
    for name, scores in evaluation.scores.items():
        pts = []
        for t, s in zip(read_chains(m, name), truth, strict=True):
            full = sitk.CompositeTransform([s, resampling_transform(t, scores.frame.transform)])
            pts.append(sitk.GetArrayFromImage(displacement_field(full, template))[mask])
        y = np.stack(pts)
        means = {g: y[groups == g].mean(axis=0) for g in CONTRASTS}
        out[name] = {
            **{
                f"within_{g}_mm": float(np.linalg.norm(y[groups == g] - means[g], axis=-1).mean())
                for g in CONTRASTS
            },
            "between_mm": float(np.linalg.norm(means["t1"] - means["t2"], axis=-1).mean()),
        }
    return out


def _with_link_error(result, mm: float):
    """`result` (per-group) with its links followed by a translation of `mm` along x.

    The translation ``D`` acts in the reference frame, first: image j of another group gets
    ``T_j o L_g o D`` in place of ``T_j o L_g`` (a composite lists the first-acting last).
    """
    shift = sitk.TranslationTransform(result.reference.GetDimension())
    shift.SetOffset((mm,) + (0.0,) * (result.reference.GetDimension() - 1))
    ref_group = result.reference_group
    return dataclasses.replace(
        result,
        transforms=tuple(
            t if g == ref_group else flatten(sitk.CompositeTransform([t, shift]))
            for t, g in zip(result.transforms, result.groups, strict=True)
        ),
        links={g: flatten(sitk.CompositeTransform([t, shift])) for g, t in result.links.items()},
        resampled=(),
        seconds=0.0,
    )


def run_case(kind: str, folder: Path, worker: ElastixWorker) -> dict:
    pop = make_population(kind, dim=2, n=N_SUBJECTS, seed=SEED, contrasts=CONTRASTS, **GRID)
    manifest = write_population(pop, folder, montage=False, progress=False)
    m = load_manifest(manifest)
    images = [str(p) for p in m.images]
    names = [_stem(p) for p in images]
    seconds, results = {}, {}
    for name, kwargs in RUNS.items():
        result = register_multimodal(
            images, m.groups, **kwargs, seed=SEED, progress=False, elastix_worker=worker
        )
        result.add_to_manifest(manifest, name, out=folder / name, names=names)
        seconds[name], results[name] = result.seconds, result
        print(f"  {kind} {name}: {result.seconds:.1f} s", flush=True)
    wrong = _with_link_error(results["per-group"], LINK_ERROR_MM)
    wrong.add_to_manifest(manifest, "per-group-link-2mm", out=folder / "link-error", names=names)
    cache = folder / "cache"
    mixture = _evaluate(manifest, cache)
    single = _evaluate(dataclasses.replace(load_manifest(manifest), groups=None), cache)
    head = sitk.GetArrayFromImage(pop.template_labels) > 0
    truth = [s.subject_to_template for c in CONTRASTS for s in pop.subjects]
    error = correspondence_error(mixture, manifest, truth, mask=head)
    parts = _error_parts(mixture, manifest, truth, pop.template, head, m.groups)
    rows = {}
    for name, scores in mixture.scores.items():
        spec = scores.specificity
        mix = spec.mixture
        one = single.scores[name].specificity
        rows[name] = {
            "specificity": spec.value,
            "stderr": spec.stderr,
            "per_group": {str(g): float(v) for g, v in zip(mix.groups, mix.values, strict=True)},
            "per_group_stderr": {
                str(g): float(v) for g, v in zip(mix.groups, mix.stderrs, strict=True)
            },
            "nearest_counts": mix.nearest_counts.tolist(),
            "single_gaussian": one.value,
            "single_gaussian_stderr": one.stderr,
            "true_error_mm": error[name],
            **parts[name],
            "seconds": seconds.get(name),  # None: no registration of its own
        }
    return {
        "kind": kind,
        "n_subjects": N_SUBJECTS,
        "n_images": len(images),
        "grid": list(pop.template.GetSize()),
        "spacing_mm": pop.template.GetSpacing()[0],
        "n_samples": N_SAMPLES,
        "registrations": rows,
    }


def _table(case: dict) -> str:
    head = [
        "registration",
        "mixture spec. (s.e.)",
        "T1 part",
        "T2 part",
        "T1→T2 / T2→T1 nearest",
        "one-Gaussian spec.",
        "true error (mm)",
        "within T1",
        "within T2",
        "T1–T2 gap",
        "time (s)",
    ]
    lines = ["| " + " | ".join(head) + " |", "|---" + "|--:" * (len(head) - 1) + "|"]
    for name, r in case["registrations"].items():
        c = np.asarray(r["nearest_counts"])
        cells = [
            name,
            f"{r['specificity']:.4g} ({r['stderr']:.2g})",
            f"{r['per_group']['t1']:.4g}",
            f"{r['per_group']['t2']:.4g}",
            f"{c[0, 1]} / {c[1, 0]}",
            f"{r['single_gaussian']:.4g}",
            f"{r['true_error_mm']:.2f}",
            f"{r['within_t1_mm']:.2f}",
            f"{r['within_t2_mm']:.2f}",
            f"{r['between_mm']:.2f}",
            "–" if r["seconds"] is None else f"{r['seconds']:.0f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(cases: dict, path: Path) -> None:
    """Per population, mixture specificity against the true correspondence error."""
    import matplotlib  # noqa: PLC0415 - only for the figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415
    from matplotlib.ticker import FormatStrFormatter  # noqa: PLC0415

    style = {
        "truth": ("k", "*"),
        "joint": ("C0", "o"),
        "per-group": ("C1", "s"),
        "joint-affine": ("C0", "^"),
        "per-group-affine": ("C1", "v"),
        "per-group-link-2mm": ("C3", "D"),
    }
    fig, axes = plt.subplots(1, len(cases), figsize=(5.2 * len(cases), 4.2), squeeze=False)
    for ax, (kind, case) in zip(axes[0], cases.items(), strict=True):
        regs = case["registrations"]
        for name, r in regs.items():
            colour, marker = style.get(name, ("grey", "x"))
            ax.errorbar(
                r["true_error_mm"],
                r["specificity"],
                yerr=2 * r["stderr"],
                color=colour,
                marker=marker,
                ls="none",
                label=name,
            )
        if "per-group-link-2mm" in regs:  # the link error: the truth moves, the mixture not
            a, b = regs["per-group"], regs["per-group-link-2mm"]
            ax.annotate(
                "",
                xy=(b["true_error_mm"], b["specificity"]),
                xytext=(a["true_error_mm"], a["specificity"]),
                arrowprops={"arrowstyle": "->", "color": "C3"},
            )
        ax.set(
            xlabel="true mean correspondence error (mm)",
            ylabel="mixture specificity (L1; lower is better)",
            title=f"{kind} 2D: {case['n_subjects']} subjects x (T1, T2)",
        )
        ax.set_yscale("log")
        for axis in (ax.yaxis.set_major_formatter, ax.yaxis.set_minor_formatter):
            axis(FormatStrFormatter("%g"))
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> dict:
    t0 = time.perf_counter()
    cases = {}
    with tempfile.TemporaryDirectory(prefix="bench-multimodal-") as tmp, ElastixWorker() as w:
        for kind in KINDS:
            cases[kind] = run_case(kind, Path(tmp) / kind, w)
    for kind, case in cases.items():
        print(
            f"\n### {kind} 2D: {case['n_subjects']} subjects x T1, T2 "
            f"({case['grid'][0]}^2 at {case['spacing_mm']:g} mm), M = {case['n_samples']}, "
            "L1\n"
        )
        print(_table(case))
    seconds = time.perf_counter() - t0
    print(f"\n({seconds:.0f} s)")
    plot(cases, Path(__file__).resolve().parent.parent / "docs" / "multimodal_benchmark.png")
    return {"cases": cases, "seconds": seconds}


if __name__ == "__main__":
    main()
