"""Label memberships: the sparse exact resampling against the dense one-hot ``sitk.Resample``.

The 3D phantom's label map (26 labels plus background, ``data_synth.phantom``) is resampled
onto a grid of its own size through a composite transform like a registration's: a smooth
displacement field (plane waves, up to 4 mm) followed by an affine (rotation, scaling, shear,
translation). Side by side in one run, on the same inputs:

* dense: ``itk_nrreval.io.frame.resample_memberships`` for one image -- the float32 one-hot
  vector image (27 channels) through one linear ``sitk.Resample``, (1, 27, *shape) float32;
* sparse: ``itk_nrreval.io._memberships.resample_label_memberships``.

Wall and CPU (process) time are the medians of a few repeats; the results are checked to
agree to 1e-6 at every voxel. Peak memory is the largest resident-set growth seen while one
call runs (sampled every 2 ms from ``/proc/self/statm``), each in a fresh process whose
allocator returns freed memory to the system (``MALLOC_MMAP_THRESHOLD_``, glibc), so that
memory freed by earlier calls cannot hide the growth. The 2 mm case is the real one
(100 x 118 x 95 voxels); the 1 mm case (182 x 218 x 182) runs the sparse method only -- the
dense one would hold three 27-channel float32 copies of the grid (about 2.3 GB).
"""

from __future__ import annotations

import ctypes
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import SimpleITK as sitk

from data_synth.phantom import make_phantom
from itk_nrreval.io._images import Geometry
from itk_nrreval.io._memberships import resample_label_memberships
from itk_nrreval.io.frame import resample_memberships

SEED = 20261123
REPEATS_DENSE = 3
REPEATS_SPARSE = 7
CASES = {
    # name: (spacing mm, ITK size (x, y, z) or None for the phantom's default field of view)
    "2 mm": (2.0, None),
    "1 mm": (1.0, (182, 218, 182)),
}


def _inputs(spacing: float, size) -> tuple[sitk.Image, sitk.Transform, Geometry]:
    """The phantom's label map, a field-then-affine transform, and the grid (the map's own)."""
    rng = np.random.default_rng(SEED)
    labels = make_phantom(dim=3, spacing=spacing, size=size).labels
    grid = Geometry.from_image(labels)
    field_img = sitk.GetImageFromArray(_smooth_displacement(grid, rng), isVector=True)
    grid.apply_to(field_img)
    field = sitk.DisplacementFieldTransform(sitk.Cast(field_img, sitk.sitkVectorFloat64))
    del field_img
    affine = sitk.AffineTransform(3)
    c, s = np.cos(0.12), np.sin(0.12)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    affine.SetMatrix((rot @ (np.eye(3) + 0.03 * rng.standard_normal((3, 3)))).ravel().tolist())
    affine.SetTranslation((3.3, -2.1, 1.7))
    # sitk applies its list from the back: the field first, then the affine
    return labels, sitk.CompositeTransform([affine, field]), grid


def _smooth_displacement(grid: Geometry, rng: np.random.Generator) -> np.ndarray:
    """(*shape, 3) float64 mm, at most 4 mm: per component a sum of three random plane waves
    of wavelength 60-120 mm (identity direction assumed: the phantom's grids have it)."""
    axes = [
        o + s * np.arange(n) for o, s, n in zip(grid.origin, grid.spacing, grid.size, strict=True)
    ]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij", sparse=True)
    u = np.zeros((*grid.shape, 3))
    for c in range(3):
        for _ in range(3):
            k = rng.normal(size=3)
            k *= 2 * np.pi / rng.uniform(60.0, 120.0) / np.linalg.norm(k)
            u[..., c] += np.sin(k[0] * x + k[1] * y + k[2] * z + rng.uniform(0, 2 * np.pi))
    u *= 4.0 / np.abs(u).max()
    return u


def _rss() -> int | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return None


def _peak_growth(fn) -> tuple[object, float | None]:
    """Run fn(); return its result and the peak RSS growth (MB) seen while it ran."""
    try:  # give free heap memory back first, so that reusing it shows as growth
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    base = _rss()
    if base is None:
        return fn(), None
    peak = [base]
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            peak[0] = max(peak[0], _rss())
            time.sleep(0.002)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        out = fn()
    finally:
        done.set()
        watcher.join()
    peak[0] = max(peak[0], _rss())
    return out, (peak[0] - base) / 2**20


def _timed(fn, repeats: int) -> tuple[object, float, float]:
    """Result of the last call, median wall seconds, median CPU seconds (all threads)."""
    walls, cpus = [], []
    out = None
    for _ in range(repeats):
        del out
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return out, float(np.median(walls)), float(np.median(cpus))


def _case(name: str, spacing: float, size, *, dense: bool) -> dict:
    labels, transform, grid = _inputs(spacing, size)
    values = np.unique(sitk.GetArrayViewFromImage(labels))

    def sparse_call():
        return _call("sparse", labels, transform, grid, values)

    sparse_call()  # compile (numba, cached on disk) outside the timing
    sparse, sparse_wall, sparse_cpu = _timed(sparse_call, REPEATS_SPARSE)
    sparse_mb = _peak_in_fresh_process(name, "sparse")
    n = int(np.prod(grid.shape))
    out = {
        "case": name,
        "size_xyz": list(grid.size),
        "spacing_mm": spacing,
        "n_voxels": n,
        "n_labels": int(values.size),
        "sparse_s": sparse_wall,
        "sparse_cpu_s": sparse_cpu,
        "sparse_peak_mb": sparse_mb,
        "nnz": int(sparse.index.size),
        "entries_per_voxel": sparse.index.size / n,
        "sparse_result_mb": (sparse.index.nbytes + sparse.weight.nbytes) / 2**20,
        "dense_result_mb": values.size * n * 4 / 2**20,
    }
    if dense:

        def dense_call():
            return _call("dense", labels, transform, grid, values)

        ref, dense_wall, dense_cpu = _timed(dense_call, REPEATS_DENSE)
        err = float(np.max(np.abs(sparse.dense() - ref[0])))
        del ref
        dense_mb = _peak_in_fresh_process(name, "dense")
        out.update(
            dense_s=dense_wall,
            dense_cpu_s=dense_cpu,
            dense_peak_mb=dense_mb,
            ratio=dense_wall / sparse_wall,
            ratio_cpu=dense_cpu / sparse_cpu,
            max_abs_diff=err,
            agree_1e6=err <= 1e-6,
        )
    return out


def _call(method: str, labels, transform, grid: Geometry, values):
    if method == "sparse":
        return resample_label_memberships(labels, transform, grid, values=values)
    return resample_memberships([labels], [transform], grid, values=values, progress=False)


def _peak_here(name: str, method: str) -> float | None:
    """Peak RSS growth (MB) of one call of `method` on case `name`, in this process."""
    spacing, size = CASES[name]
    labels, transform, grid = _inputs(spacing, size)
    values = np.unique(sitk.GetArrayViewFromImage(labels))
    # warm up (load the compiled kernels) on four planes of the grid
    small = Geometry((*grid.size[:-1], 4), grid.spacing, grid.origin, grid.direction)
    _call(method, labels, transform, small, values)
    return _peak_growth(lambda: _call(method, labels, transform, grid, values))[1]


def _peak_in_fresh_process(name: str, method: str) -> float | None:
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_=str(128 * 1024))
    out = subprocess.run(
        [sys.executable, __file__, "--peak", name, method],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _mb(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.0f}"


def main() -> dict:
    results = [
        _case(name, spacing, size, dense=name == "2 mm") for name, (spacing, size) in CASES.items()
    ]
    print(
        "One 3D label map (the phantom: 26 labels + background) resampled as fuzzy memberships "
        "through a displacement field followed by an affine, onto a grid of its own size. "
        f"Median of {REPEATS_DENSE} (dense) / {REPEATS_SPARSE} (sparse) runs; CPU time counts "
        f"all threads ({os.cpu_count()} cores); peak = largest RSS growth during one call.\n"
    )
    print(
        "| grid | labels | dense (s) | dense CPU (s) | dense peak (MB) | sparse (s) "
        "| sparse CPU (s) | sparse peak (MB) | speed-up | max abs diff |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in results:
        size = "x".join(str(s) for s in r["size_xyz"])
        if "dense_s" in r:
            dense = f"{r['dense_s']:.2f} | {r['dense_cpu_s']:.2f} | {_mb(r['dense_peak_mb'])}"
            ratio = f"{r['ratio']:.1f}x (CPU {r['ratio_cpu']:.1f}x)"
            diff = f"{r['max_abs_diff']:.1e}"
        else:
            dense, ratio, diff = "not run | | ", "", ""
        print(
            f"| {r['case']} {size} | {r['n_labels']} | {dense} | {r['sparse_s']:.3f} "
            f"| {r['sparse_cpu_s']:.3f} | {_mb(r['sparse_peak_mb'])} | {ratio} | {diff} |"
        )
    print()
    print("| grid | stored entries per voxel | sparse result (MB) | dense result (MB) |")
    print("|---|---|---|---|")
    for r in results:
        print(
            f"| {r['case']} | {r['entries_per_voxel']:.3f} | {r['sparse_result_mb']:.0f} "
            f"| {r['dense_result_mb']:.0f} |"
        )
    return {"results": results}


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--peak":
        print(json.dumps(_peak_here(sys.argv[2], sys.argv[3])))
    else:
        main()
