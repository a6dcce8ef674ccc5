"""The per-image task at 1 mm: its parts, its floor, and its cache entry (issue 30).

One 3D phantom subject at 1 mm (200 x 236 x 190 voxels, 9.0 M; 26 labels) and two
registrations of it: ``field`` (its true template-to-subject transform, an affine map and a
1 mm displacement field) and ``affine`` (the affine part alone); and ``field, no labels``,
the field registration of the image alone, as a cohort without label maps runs it. For
each, the task the pipeline runs per image and registration
(:class:`itk_nrreval._pipeline._image_tasks.ResampleImage`) runs on a cold cache, in a fresh
process on one thread (SimpleITK and numba), with its parts timed by wrapping the functions
it calls:

- ``read``: the image and label map read from disk;
- ``resample``: the image resampled onto the common grid (since issue 30, when it shares the
  label map's grid, from the memberships' own sampling of the transform: their kernel);
- ``memberships``: the label map's sparse memberships on the common grid (since issue 30's
  ``transforms.PointMap``, with the slab-by-slab sampling of the transform they and the
  image's values share, which ``other`` held before);
- ``plausibility``: folding, SDlogJ, the Jacobian histogram and inverse consistency, of
  which ``invert`` (the numerical inverse; since issue 30 the coarse inverse alone) and
  ``round trip`` (``T^-1(T(p))`` sampled; since issue 30 with the inverse refined at those
  points; before, the plausibility call timed again without inverse consistency gives it);
- ``affine fit``: the transform's closest affine map (since issue 30 from the
  plausibility's own sampling of the transform, and timed apart from it);
- ``coverage``: which common-grid voxels the transform brings the image's field of view to
  (since issue 30, measured with the plausibility in a task of its own before any image is
  resampled, :class:`~itk_nrreval._pipeline._image_tasks.MeasureTransform`; the two tasks are
  timed together);
- ``cache write``: the entries written (hashed and renamed into place);
- ``other``: the rest of the task.

A third run times the frame-estimate task
(:class:`itk_nrreval._pipeline._common_frame.EstimateFrame`) of the ``field`` registration
with ``affine`` as the common frame -- ``F = T_field^-1 o T_affine`` sampled on the common
grid, the task a registration whose frame is not the common one runs per image -- with
its inversion apart (since issue 30 the coarse inverse alone: the refinement runs at the
grid's points as it is sampled), and its cache entry's size.

The floor is SimpleITK's own ``sitk.Resample`` of the same float32 volume through the same
composed transform onto the same grid (linear), timed in the same process; the task's cost
is reported as a ratio to it. Times are CPU seconds of the one thread (``process_time``),
which other processes on the machine do not inflate. The cache entry's size is its files'
bytes on disk.

The task runs twice and the second run is timed: the first compiles numba's kernels when
their disk cache is cold and brings the files into the page cache. The round trip is timed
directly where the code has it apart (``plausibility._mean_round_trip``), otherwise as the
plausibility timed again without inverse consistency, subtracted.

A fourth run times reading the ``field`` registration's ``.h5`` as its pieces: ITK's reader
with the composite taken apart (what the tasks did before) against h5py
(:func:`itk_nrreval.io.transforms.transform_pieces`, since issue 30), as a ratio.

``python benchmarks/run_all.py image_task`` runs it (about 5 minutes; the subject is
generated once into ``benchmarks/out/image_task_1mm`` and reused).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
UNLABELLED = ", no labels"
DATA = ROOT / "benchmarks" / "out" / "image_task_1mm"
SPACING_MM = 1.0
PARTS = (
    "read",
    "resample",
    "memberships",
    "plausibility",
    "invert",
    "round trip",
    "affine fit",
    "coverage",
    "cache write",
    "other",
)


def subject() -> dict:
    """The subject's files (generated on first use): image, labels, the two transforms."""
    info_path = DATA / "subject.json"
    if info_path.exists():
        return json.loads(info_path.read_text())
    import SimpleITK as sitk
    import yaml

    from data_synth.population import make_population
    from data_synth.writing import write_population

    pop = make_population("phantom", dim=3, n=1, seed=30, spacing=SPACING_MM)
    manifest = yaml.safe_load(
        write_population(pop, DATA, montage=False, progress=False).read_text()
    )
    affine = sitk.AffineTransform(pop.subjects[0].template_to_subject.GetNthTransform(0))
    mat = DATA / "affine" / "s00.mat"
    mat.parent.mkdir(exist_ok=True)
    sitk.WriteTransform(affine, str(mat))
    truth = manifest["registrations"]["truth"]
    info = {
        "image": str(DATA / manifest["images"][0]),
        "labels": str(DATA / manifest["labels"][0]),
        "reference": str(DATA / truth["reference"]),
        "transforms": {"field": str(DATA / truth["transforms"][0]), "affine": str(mat)},
    }
    info_path.write_text(json.dumps(info))
    return info


def _task_modules() -> tuple:
    """The modules in which the pipeline's per-image tasks and its frame-estimate task look
    up what they call, and the class of the context every task takes: since issue 43
    ``_pipeline`` is a package of modules, before it one module."""
    from itk_nrreval import _pipeline

    try:
        from itk_nrreval._pipeline import _common_frame, _image_tasks, _task_keys
    except ImportError:
        return _pipeline, _pipeline, _pipeline._Context
    return _image_tasks, _common_frame, _task_keys.TaskContext


def _run_task_objects(root, grid, info, labels, item, own) -> list[tuple]:
    """The two per-image tasks as frozen task objects run through the cache (issue 43):
    ``(kind, key, reused, meta)`` each."""
    from itk_nrreval._pipeline import _image_tasks, _tasks

    common = {"grid": grid, "image": Path(info["image"]), "item": item, "reg_grid": grid}
    common |= {"frame": ("identity",), "frame_digest": "identity"}
    measure = _image_tasks.MeasureTransform(
        **common, mask_key=None, reg_mask_key=None, inverse_consistency=True
    )
    resample = _image_tasks.ResampleImage(
        **common,
        labels=labels,
        interpolation="linear",
        label_resampling=("linear", None),
        own_values=None if own is None else tuple(own),
    )
    out = []
    for task in (measure, resample):
        key, meta, reused = _tasks.run_cached(root, task)
        out.append((task.kind, key, reused, meta))
    return out


def _measure(info: dict, name: str) -> dict:
    """One registration's task on a cold cache, its parts, and the floor (this process)."""
    import tempfile

    import numpy as np
    import SimpleITK as sitk

    from itk_nrreval.io import plausibility
    from itk_nrreval.io._cache import DiskCache
    from itk_nrreval.io._images import Geometry, read_image
    from itk_nrreval.io.frame import label_values, resampling_transform
    from itk_nrreval.io.transforms import chain_transform

    tasks, _frames, Context = _task_modules()
    spent = dict.fromkeys(PARTS, 0.0)

    def timed(part, fn):
        def wrapper(*args, **kwargs):
            t0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[part] += time.process_time() - t0

        return wrapper

    # the task's own calls, wrapped where it looks them up
    tasks.read_image = timed("read", tasks.read_image)
    tasks.resample_images = timed("resample", tasks.resample_images)
    tasks.resample_label_memberships = timed("memberships", tasks.resample_label_memberships)
    # since issue 30 the image is resampled inside the memberships' pass, from their sampling
    shared_sampling = hasattr(tasks, "resample_image_and_memberships")
    if shared_sampling:
        from itk_nrreval.io import _memberships

        tasks.resample_image_and_memberships = timed(
            "memberships", tasks.resample_image_and_memberships
        )
        _memberships._linear_values = timed("resample", _memberships._linear_values)
    tasks.deformation_measures = timed("plausibility", tasks.deformation_measures)
    if hasattr(plausibility, "PointwiseInverse"):  # since issue 30: the coarse inverse
        plausibility.PointwiseInverse = timed("invert", plausibility.PointwiseInverse)
    else:
        plausibility.invert = timed("invert", plausibility.invert)
    # since issue 30 the affine fit adds up the measures' own sampling (a part of them)
    shared_fit = hasattr(plausibility, "_AffineSums")
    if shared_fit:
        plausibility._AffineSums.add = timed("affine fit", plausibility._AffineSums.add)
    else:
        tasks.affine_fit = timed("affine fit", tasks.affine_fit)
    DiskCache.put = timed("cache write", DiskCache.put)
    direct_round_trip = hasattr(plausibility, "_mean_round_trip")  # since issue 30
    if direct_round_trip:
        plausibility._mean_round_trip = timed("round trip", plausibility._mean_round_trip)

    grid = Geometry.from_image(read_image(info["reference"], what="reference image"))
    unlabelled = name.endswith(UNLABELLED)  # the image alone, without its label map
    name = name.removesuffix(UNLABELLED)
    labels = None if unlabelled else Path(info["labels"])
    own = None if unlabelled else [int(v) for v in label_values([labels]) if v != 0]
    item = Path(info["transforms"][name])
    # since issue 30 the transform's measures are a task of their own, before resampling
    # since issue 43 public names of their module (_image_tasks)
    measures_task = getattr(tasks, "measures_task", getattr(tasks, "_measures_task", None))
    resample_task = getattr(tasks, "resample_task", getattr(tasks, "_resample_task", None))
    two_tasks = measures_task is not None
    if two_tasks:
        tasks.covered_voxels = timed("coverage", tasks.covered_voxels)
    with tempfile.TemporaryDirectory(prefix="bench-image-task-") as root:
        ctx = Context(root, grid, None, True)
        args = (ctx, Path(info["image"]), labels, item, ("identity",), "identity", grid)

        def run_tasks() -> list[tuple]:
            if hasattr(tasks, "MeasureTransform"):  # since issue 43: task objects
                return _run_task_objects(root, grid, info, labels, item, own)
            if not two_tasks:
                return [("resampled", *resample_task(*args, "linear", None, own))]
            measured = measures_task(*args[:2], *args[3:], None)
            return [
                ("measures", *measured),
                ("resampled", *resample_task(*args, "linear", own)),
            ]

        # a first run compiles the numba kernels (when their disk cache is cold) and reads
        # the files into the page cache: not timed
        run_tasks()
        for kind in ("resampled", "measures"):
            shutil.rmtree(Path(root) / kind, ignore_errors=True)
        spent.update(dict.fromkeys(PARTS, 0.0))
        t0 = time.process_time()
        results = run_tasks()
        total = time.process_time() - t0
        assert not any(reused for _kind, _key, reused, _meta in results)
        files = {}
        for kind, key, _reused, _meta in results:
            folder = DiskCache(root)._folder(kind, key)
            files.update({f"{kind}/{p.name}": p.stat().st_size for p in folder.iterdir()})

    nested = ("invert", "round trip", "other")  # parts of the plausibility
    if shared_fit:
        nested += ("affine fit",)
    if shared_sampling:
        nested += ("resample",)  # a part of the memberships' pass
    spent["other"] = total - sum(v for k, v in spent.items() if k not in nested)
    if shared_sampling:
        spent["memberships"] -= spent["resample"]
    t = chain_transform(item)
    if not direct_round_trip:  # plausibility with inverse consistency minus without
        t0 = time.process_time()
        plausibility.deformation_measures(t, grid, inverse_consistency=False)  # not wrapped
        without = time.process_time() - t0
        spent["round trip"] = max(spent["plausibility"] - spent["invert"] - without, 0.0)
    spent["plausibility"] -= spent["invert"] + spent["round trip"]  # the rest of it
    if shared_fit:
        spent["plausibility"] -= spent["affine fit"]

    # the floor: SimpleITK's Resample of the same volume through the same composed transform
    image = sitk.ReadImage(info["image"])
    full = resampling_transform(t, sitk.TranslationTransform(3))
    t0 = time.process_time()
    sitk.Resample(
        image,
        list(grid.size),
        full,
        sitk.sitkLinear,
        list(grid.origin),
        list(grid.spacing),
        list(grid.direction),
        0.0,
        image.GetPixelID(),
    )
    floor = time.process_time() - t0
    return {
        "registration": name + (UNLABELLED if unlabelled else ""),
        "voxels": int(np.prod(grid.shape)),
        "total_s": total,
        "parts_s": spent,
        "floor_s": floor,
        "ratio_to_floor": total / floor,
        "cache_mb": sum(files.values()) / 2**20,
        "cache_files_mb": {k: v / 2**20 for k, v in sorted(files.items())},
    }


def _estimate_call(frames, ctx, common, item, grid, *, two_entries: bool) -> tuple:
    """``(run, key)``: the frame-estimate task of `frames` for the mean and the spread, as a
    call that returns whether it was cached: since issue 43 a task object
    (``EstimateFrame``) run through the cache wrapper, before it a function."""
    if hasattr(frames, "EstimateFrame"):
        import numpy as np

        from itk_nrreval._pipeline import _tasks

        task = frames.EstimateFrame(
            grid=grid,
            common_item=common,
            item=item,
            reg_grid=grid,
            stored=np.dtype(frames._STORED_ESTIMATE).str,
            for_mean=True,
        )
        return (lambda: _tasks.run_cached(ctx.root, task)[2]), _tasks.key_of(task)
    key = frames._estimate_key(ctx, common, item, grid)
    args = (ctx, key, common, item, grid, *((True,) if two_entries else ()))
    return (lambda: frames._estimate_task(*args)), key


def _measure_estimate(info: dict) -> dict:
    """The frame-estimate task of the field registration, when the affine one is the common
    frame: ``F_i = T_field^-1 o T_affine`` sampled on the common grid, on a cold cache."""
    import tempfile

    from itk_nrreval.io import frame
    from itk_nrreval.io._cache import DiskCache
    from itk_nrreval.io._images import Geometry, read_image

    _tasks, frames, Context = _task_modules()
    spent = {"invert": 0.0}
    # since issue 30 the estimate's inverse is pointwise: its coarse inverse is timed
    name = "PointwiseInverse" if hasattr(frame, "PointwiseInverse") else "invert"
    invert = getattr(frame, name)

    def timed_invert(*args, **kwargs):
        t0 = time.process_time()
        try:
            return invert(*args, **kwargs)
        finally:
            spent["invert"] += time.process_time() - t0

    setattr(frame, name, timed_invert)
    grid = Geometry.from_image(read_image(info["reference"], what="reference image"))
    common, item = Path(info["transforms"]["affine"]), Path(info["transforms"]["field"])
    with tempfile.TemporaryDirectory(prefix="bench-image-task-") as root:
        # since issue 30: float32 for the mean (removed once added up) and 16-bit steps for
        # the spread, two entries
        kinds = ("estimate", "estimate_steps") if hasattr(frame, "in_steps") else ("estimate",)
        ctx = Context(root, grid, None, True)
        run, key = _estimate_call(frames, ctx, common, item, grid, two_entries=len(kinds) == 2)
        run()  # warm-up, as in _measure
        for kind in kinds:
            shutil.rmtree(Path(root) / kind)
        spent["invert"] = 0.0
        t0 = time.process_time()
        reused = run()
        total = time.process_time() - t0
        assert not reused
        size = sum(
            p.stat().st_size for kind in kinds for p in DiskCache(root)._folder(kind, key).iterdir()
        )
    return {
        "registration": "frame estimate",
        "total_s": total,
        "invert_s": spent["invert"],
        "cache_mb": size / 2**20,
    }


def _measure_read(info: dict, repeats: int = 5) -> dict:
    """Reading the field registration's ``.h5`` (an affine map and a 1 mm displacement
    field) as its pieces: ``leaves(sitk.ReadTransform(path))`` (ITK's reader, then the
    composite taken apart: what the tasks did before) against
    :func:`~itk_nrreval.io.transforms.transform_pieces` (h5py, since issue 30), the least CPU
    seconds of `repeats` reads each, alternated, in this process."""
    import SimpleITK as sitk

    from itk_nrreval.io.transforms import leaves, transform_pieces

    path = Path(info["transforms"]["field"])
    spent = {"itk": [], "pieces": []}
    for _ in range(repeats):
        for name, read in (
            ("itk", lambda: leaves(sitk.ReadTransform(str(path)))),
            ("pieces", lambda: transform_pieces(path)),
        ):
            t0 = time.process_time()
            pieces = read()
            spent[name].append(time.process_time() - t0)
            del pieces
    itk, ours = min(spent["itk"]), min(spent["pieces"])
    return {"registration": "read", "itk_s": itk, "pieces_s": ours, "ratio": itk / ours}


def _one_thread_env() -> dict:
    env = dict(os.environ)
    env.update(
        ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS="1",
        NUMBA_NUM_THREADS="1",
        OMP_NUM_THREADS="1",
        OPENBLAS_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        PYTHONPATH=str(ROOT),
    )
    return env


def run(name: str) -> dict:
    """One registration, measured in a fresh single-threaded process."""
    subject()  # generated here, once, not in every measuring process
    cmd = [sys.executable, __file__, "--run", name]
    out = subprocess.run(
        cmd, check=True, capture_output=True, text=True, env=_one_thread_env()
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def main() -> dict:
    runs = [run(name) for name in ("field", "affine", "field" + UNLABELLED)]
    estimate = run("estimate")
    print("| part (CPU s, one thread) | " + " | ".join(r["registration"] for r in runs) + " |")
    print("|---|" + "---|" * len(runs))
    for part in PARTS:
        print(f"| {part} | " + " | ".join(f"{r['parts_s'][part]:.2f}" for r in runs) + " |")
    print("| **task** | " + " | ".join(f"**{r['total_s']:.2f}**" for r in runs) + " |")
    print("| sitk.Resample floor | " + " | ".join(f"{r['floor_s']:.2f}" for r in runs) + " |")
    print("| task / floor | " + " | ".join(f"{r['ratio_to_floor']:.1f}x" for r in runs) + " |")
    print("| cache entry (MB) | " + " | ".join(f"{r['cache_mb']:.0f}" for r in runs) + " |")
    for r in runs:
        files = ", ".join(f"{k} {v:.1f}" for k, v in r["cache_files_mb"].items())
        print(f"\n{r['registration']}: cache files (MB): {files}")
    print(
        f"\nframe estimate of the field registration (affine common): "
        f"{estimate['total_s']:.2f} s (inversion {estimate['invert_s']:.2f} s), "
        f"cache entry {estimate['cache_mb']:.0f} MB"
    )
    read = run("read")
    print(
        f"\nreading the field's .h5 as pieces (CPU s): ITK's reader and the composite taken "
        f"apart {read['itk_s']:.2f}, h5py {read['pieces_s']:.2f} ({read['ratio']:.1f}x)"
    )
    return {"spacing_mm": SPACING_MM, "runs": runs, "frame_estimate": estimate, "read": read}


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--run":
        import SimpleITK as sitk

        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
        info = subject()
        name = sys.argv[2]
        if name == "estimate":
            out = _measure_estimate(info)
        elif name == "read":
            out = _measure_read(info)
        else:
            out = _measure(info, name)
        print(json.dumps(out))
    else:
        results = main()
        out = ROOT / "benchmarks" / "out" / "image_task.json"
        out.write_text(json.dumps(results, indent=2) + "\n")
