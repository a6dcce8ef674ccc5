"""The shape model's generalization as label-free evidence: issue 41's idea (c), NOT KEPT.

For each registration of a case, the displacement fields ``u_i(p) = T_i(p) - p`` (mm) of
every subject but the reference (registered to itself), on the registration's reference grid
inside the case's mask, make a shape model (their PCA). Its generalization is the
leave-one-out error: each subject's field minus its projection on the mean and principal
modes of the others', RMS over the mask's voxels (mm), averaged over subjects. An affine
registration's fields lie in a space of few dimensions that the others span, so its
generalization is about zero; a rough registration adds subject-specific displacement that
no other subject predicts.

Measured on every saved ``families_*`` case of the verdict benchmark (all its splits):
Spearman of the shape generalization against the true error over each case's deformable
registrations, beside the same for SDlogJ and specificity (``docs/verdict.md``, "The shape
model's generalization"). It tracks the true error as SDlogJ does, because both measure the
deformation a registration adds; it is no evidence beyond the roughness the verdict reads
already, and it ranks the affine registration best.

``python benchmarks/bench_shape_generalization.py [--compute]``: ``--compute`` first
measures the cases that lack it (``shape.json`` in the case's folder; seconds a 2D case, a
minute or two a 3D one); then the table is printed and written to
``benchmarks/out/verdict/shape.md``.
"""

from __future__ import annotations

import collections
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import yaml
from scipy.stats import spearmanr

from itk_nrreval.io._images import Geometry, read_image
from itk_nrreval.io._transform_io import read_transform
from itk_nrreval.io.frame import points_minus_grid

HERE = Path(__file__).resolve().parent
SHAPE_JSON = "shape.json"


def _verdict_bench():
    spec = importlib.util.spec_from_file_location("bench_verdict", HERE / "bench_verdict.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def leave_one_out_error(fields: np.ndarray) -> float:
    """Mean over subjects of the RMS (over voxels) of each field's residual after its
    projection on the mean and principal modes of the others'.

    Parameters
    ----------
    fields : ndarray of shape (n_subjects, n_voxels, dim)
        Displacements (mm).
    """
    n, n_voxels = fields.shape[:2]
    x = fields.reshape(n, -1)
    errors = []
    for i in range(n):
        others = np.delete(x, i, axis=0)
        mean = others.mean(axis=0)
        _, s, vt = np.linalg.svd(others - mean, full_matrices=False)
        modes = vt[s > 1e-9 * s[0]] if s.size and s[0] > 0 else vt[:0]
        r = x[i] - mean
        r = r - modes.T @ (modes @ r)
        errors.append(np.sqrt(np.sum(r**2) / n_voxels))
    return float(np.mean(errors))


def measure(case: Path) -> dict[str, float]:
    """Every registration's shape generalization (mm) in saved case `case`."""
    manifest = yaml.safe_load((case / "manifest.yaml").read_text())
    mask = sitk.GetArrayFromImage(read_image(str(case / manifest["mask"]))).astype(bool)
    out = {}
    for name, reg in manifest["registrations"].items():
        grid = Geometry.from_image(read_image(str(case / reg["reference"])))
        dim = len(grid.shape)
        ref = reg.get("reference_index", 0)
        fields = np.stack(
            [
                points_minus_grid(read_transform(str(case / t)), grid).reshape(-1, dim)[
                    mask.ravel()
                ]
                for i, t in enumerate(reg["transforms"])
                if i != ref
            ]
        )
        out[name] = leave_one_out_error(fields)
    tmp = case / (SHAPE_JSON + ".tmp")
    tmp.write_text(json.dumps(out) + "\n")
    tmp.replace(case / SHAPE_JSON)
    return out


def main(argv: list[str] | None = None) -> dict:
    """The table (``rows``: its lines); `argv` ``["--compute"]`` measures the cases that lack
    it first (``run_all.py`` passes nothing)."""
    argv = [] if argv is None else argv
    bv = _verdict_bench()
    cases = sorted(p for p in bv.OUT.glob("families_*") if (p / "truth.json").exists())
    if not cases:
        print("no saved cases: run `python benchmarks/bench_verdict.py --new` first")
        return {"rows": []}
    by_split = collections.defaultdict(list)
    for case in cases:
        path = case / SHAPE_JSON
        if not path.exists() and "--compute" not in argv:
            continue
        shape = json.loads(path.read_text()) if path.exists() else measure(case)
        truth = json.loads((case / "truth.json").read_text())["true_error_mm"]
        regs = json.loads((case / "results.json").read_text())["registrations"]
        deformable = [n for n in shape if n != "affine"]
        measures = {
            "shape generalization": shape,
            "SDlogJ": {n: regs[n]["plausibility"]["sdlogj"] for n in shape},
            "specificity": {n: regs[n]["specificity"]["value"] for n in shape},
        }
        by_split[bv.split_of(case.name)].append(
            [
                spearmanr([v[n] for n in deformable], [truth[n] for n in deformable])[0]
                for v in measures.values()
            ]
        )
    names = ("shape generalization", "SDlogJ", "specificity")
    lines = [
        "| split | cases | " + " | ".join(names) + " |",
        "|---|--:|" + "--:|" * len(names),
    ]
    for split, rows in sorted(by_split.items(), key=lambda item: bv.SPLITS.index(item[0])):
        a = np.asarray(rows, float)
        cells = [f"{np.nanmean(c):+.2f} ({np.nanmin(c):+.2f})" for c in a.T]
        lines.append(f"| {split} | {len(rows)} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    (bv.OUT / "shape.md").write_text(text)
    return {"rows": lines[2:]}


if __name__ == "__main__":
    main(sys.argv[1:])
