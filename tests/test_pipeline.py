"""The evaluate dataflow: Dask equals in-process; the per-image cache and resume on both."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from test_evaluate import image, make_case

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.io._cache import DiskCache, digest_of

pytest.importorskip("dask.distributed")

KW = dict(n_samples=2000, seed=5, progress=False)
# the two executors: in this process, and a one-worker local Dask cluster
EXECUTORS = {"in_process": {}, "dask": {"scheduler": "local", "workers": 1}}


def _local_cluster(workers: int):
    from dask.distributed import LocalCluster

    return LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0"
    )


@pytest.fixture(scope="module")
def dask_address():
    """A one-worker local Dask cluster for this module's cache tests, reached by its address.

    Each of their Dask runs started and closed a ``"local"`` cluster of its own (10 runs,
    about 2 s of CPU each for the worker process alone); what they check is the cache on the
    Dask executor, which is the same either way (only how the client is made differs).
    ``evaluate`` starting a ``"local"`` cluster is checked by
    test_cli_local_scheduler_reports_cache and test_killed_run_restarts_from_cache[dask]
    (and in test_dask_parity and test_in_memory).
    """
    with _local_cluster(1) as cluster:
        yield cluster.scheduler_address


@pytest.fixture(scope="module")
def two_workers():
    """A running two-worker local Dask cluster, reached by its address."""
    with _local_cluster(2) as cluster:
        yield cluster


@pytest.fixture
def executor_options(executor, request) -> dict:
    """The Execution options of `executor`: none in process; on Dask, the module's cluster."""
    if executor == "in_process":
        return {}
    return {"scheduler": request.getfixturevalue("dask_address"), "workers": 1}


def with_mask(tmp_path) -> Path:
    """make_case plus a mask on the common grid (part of the template)."""
    data = make_case(tmp_path)
    mask = np.zeros((40, 40), np.uint8)
    mask[4:36, 6:34] = 1
    sitk.WriteImage(image(mask), str(tmp_path / "mask.nii.gz"))
    data["mask"] = "mask.nii.gz"
    path = tmp_path / "manifest.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def assert_same_scores(a, b, *, rel: float = 1e-10) -> None:
    assert list(a.scores) == list(b.scores)
    for name in a.scores:
        sa, sb = a.scores[name], b.scores[name]
        for key, va in sa.measures().items():
            assert sb.measures()[key] == pytest.approx(va, rel=rel, abs=1e-12), (name, key)
        assert sb.specificity.stderr == pytest.approx(sa.specificity.stderr, rel=rel)
        np.testing.assert_array_equal(sb.specificity.nearest_counts, sa.specificity.nearest_counts)
        np.testing.assert_allclose(
            sb.generalization.nearest_distances, sa.generalization.nearest_distances, rtol=rel
        )
        assert sb.frame.method == sa.frame.method
        assert sb.frame.spread_mean_mm == pytest.approx(sa.frame.spread_mean_mm, rel=rel)
        assert sb.frame.spread_max_mm == pytest.approx(sa.frame.spread_max_mm, rel=rel)
        assert sb.folded_fraction == sa.folded_fraction
        np.testing.assert_allclose(b.mean_images[name], a.mean_images[name], rtol=rel, atol=1e-10)
    assert a.ranks == b.ranks


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_distributed_equals_single_process(tmp_path, distance, two_workers):
    manifest = with_mask(tmp_path)
    single = nr.evaluate(manifest, distance=distance, **KW)
    # on a running cluster rather than one started for each run ("local", ~4 s of CPU for
    # its two worker processes): the tasks and results are the same, only how the client
    # is made differs (see dask_address)
    scaled = nr.evaluate(
        manifest,
        distance=distance,
        execution=nr.Execution(
            scheduler=two_workers.scheduler_address, workers=2, cache=tmp_path / "c"
        ),
        **KW,
    )
    assert_same_scores(single, scaled)
    assert scaled.run["workers"] == 2
    assert scaled.run["scheduler"] == two_workers.scheduler_address
    # a running cluster given by its address is left running: not evaluate's to close
    assert len(two_workers.scheduler_info["workers"]) == 2
    assert two_workers.status.name == "running"
    assert scaled.run["cache_reused"] == 0
    # the frame estimates of the two non-common registrations, every transform's measures,
    # then every resampled image
    assert scaled.run["cache_computed"] == 2 * 6 + 3 * 6 + 3 * 6
    assert scaled.options == single.options
    assert single.run["scheduler"] is None and single.run["cache_computed"] == 2 * 6 + 3 * 6 * 2


@pytest.mark.parametrize("executor", EXECUTORS)
def test_rerun_reuses_cache_and_extension_computes_only_the_new(tmp_path, executor_options):
    manifest = with_mask(tmp_path)
    cache = tmp_path / "c"
    execution = nr.Execution(cache=cache, keep_resampled=True, **executor_options)
    kw = dict(execution=execution, **KW)
    first = nr.evaluate(manifest, **kw)
    again = nr.evaluate(manifest, **kw)
    assert again.run["cache_reused"] == first.run["cache_computed"] == 12 + 18 + 18
    assert again.run["cache_computed"] == 0
    assert_same_scores(first, again, rel=0)
    # one more registration: only its own per-image results are new
    data = yaml.safe_load(manifest.read_text())
    data["registrations"]["truth_again"] = {
        "reference": "template.nii.gz",
        "frame_transform": "id0_0GenericAffine.mat",  # an identity affine
        "transforms": data["registrations"]["truth"]["transforms"],
    }
    manifest.write_text(yaml.safe_dump(data, sort_keys=False))
    extended = nr.evaluate(manifest, **kw)
    # its frame estimates, measures and resampled images
    assert extended.run["cache_computed"] == 6 + 6 + 6
    assert extended.run["cache_reused"] == 48
    # same images, same transforms, identity frame: the same scores as "truth"
    t, t2 = extended.scores["truth"], extended.scores["truth_again"]
    assert t2.specificity.value == pytest.approx(t.specificity.value, rel=1e-12)
    assert t2.overlap == pytest.approx(t.overlap, rel=1e-12)


@pytest.mark.parametrize("executor", EXECUTORS)
def test_frame_estimates_leave_the_cache_once_the_frame_and_its_spread_are_kept(
    tmp_path, executor_options
):
    """The per-image estimates of F (and F - p) are full-grid fields needed only to build F
    and its spread: about half of a 1 mm cohort's cache (issue 30). A rerun reuses F and its
    spread without them."""
    manifest = with_mask(tmp_path)
    cache = tmp_path / "c"
    kw = dict(execution=nr.Execution(cache=cache, **executor_options), **KW)
    first = nr.evaluate(manifest, **kw)
    assert not list(cache.glob("estimate/*/*/entry.json"))
    assert not list(cache.glob("frame_disp/*/*/entry.json"))
    assert len(list(cache.glob("frame/*/*/entry.json"))) == 1  # the group's estimate of F
    again = nr.evaluate(manifest, **kw)
    assert again.run["cache_computed"] == 18  # the resampled images, which left the cache too
    assert_same_scores(first, again, rel=0)
    # without the cache, the same numbers
    assert_same_scores(first, nr.evaluate(manifest, **KW), rel=0)


@pytest.mark.parametrize("executor", EXECUTORS)
def test_cache_holds_one_registrations_resampled_images_at_a_time(
    tmp_path, executor_options, monkeypatch
):
    """Issue 30: every transform's coverage is measured before any image is resampled, so a
    registration's resampled images (50 MB each at 1 mm) leave the cache once its scores
    are taken; the cache keeps the measures. Kept or not, and rerun, the same numbers."""
    from itk_nrreval._pipeline import _driver

    manifest = with_mask(tmp_path)
    cache = tmp_path / "c"
    on_disk = []
    reduce = _driver._reduce_registration

    def observed(executor_, ctx, disk, m, name, r, **kw):
        keys = {p.parent.name for p in (cache / "resampled").glob("*/*/entry.json")}
        on_disk.append((name, keys, set(r.keys)))
        return reduce(executor_, ctx, disk, m, name, r, **kw)

    monkeypatch.setattr(_driver, "_reduce_registration", observed)
    execution = nr.Execution(cache=cache, **executor_options)
    first = nr.evaluate(manifest, execution=execution, **KW)
    assert [name for name, _, _ in on_disk] == list(first.scores)
    for _name, keys, own in on_disk:
        assert keys == own and len(own) == 6  # its own images, and no other registration's
    assert not list((cache / "resampled").glob("*/*/entry.json"))
    assert len(list((cache / "measures").glob("*/*/entry.json"))) == 18
    kept_cache = tmp_path / "k"
    kept = nr.evaluate(
        manifest,
        execution=nr.Execution(cache=kept_cache, keep_resampled=True, **executor_options),
        **KW,
    )
    assert len(list((kept_cache / "resampled").glob("*/*/entry.json"))) == 18
    assert_same_scores(first, kept, rel=0)
    again = nr.evaluate(manifest, execution=execution, **KW)
    assert again.run["cache_computed"] == 18 and again.run["cache_reused"] == 12 + 18
    assert_same_scores(first, again, rel=0)


@pytest.mark.parametrize("executor", EXECUTORS)
def test_corrupt_cache_entries_are_recomputed(tmp_path, executor_options):
    manifest = with_mask(tmp_path)
    cache = tmp_path / "c"
    execution = nr.Execution(cache=cache, keep_resampled=True, **executor_options)
    kw = dict(execution=execution, **KW)
    first = nr.evaluate(manifest, **kw)
    entries = sorted((cache / "resampled").glob("*/*/entry.json"))
    assert len(entries) == 18
    # a flipped byte in one array, a truncated index in another, a deleted array in a third
    arr = entries[0].parent / "image.npy"
    raw = bytearray(arr.read_bytes())
    raw[-5] ^= 0xFF
    arr.write_bytes(bytes(raw))
    entries[1].write_text(entries[1].read_text()[:20])
    (entries[2].parent / "lab_val.npy").unlink()
    # and a transform's measures: a flipped bit of its coverage
    measures = sorted((cache / "measures").glob("*/*/covered.npy"))
    assert len(measures) == 18
    raw = bytearray(measures[0].read_bytes())
    raw[-1] ^= 0x01
    measures[0].write_bytes(bytes(raw))
    again = nr.evaluate(manifest, **kw)
    assert again.run["cache_computed"] == 4
    assert again.run["cache_reused"] == 12 + 18 + 18 - 4
    assert_same_scores(first, again, rel=0)


def slow_case(tmp_path) -> Path:
    """Bigger images (256^2, N = 12), so that a run takes a few seconds on one worker."""
    size, n = 256, 12
    y, x = np.mgrid[0:size, 0:size] / size
    lab = (1 + (x > 0.5) + 2 * (y > 0.4) + ((x - 0.5) ** 2 + (y - 0.5) ** 2 < 0.05)).astype(
        np.int16
    )
    rng = np.random.default_rng(1)
    items = []
    for i in range(n):
        img = image(lab * 50.0 + rng.normal(size=lab.shape))
        sitk.WriteImage(img, str(tmp_path / f"i{i}.nii.gz"))
        sitk.WriteImage(image(lab), str(tmp_path / f"l{i}.nii.gz"))
        disp = np.zeros((size, size, 2))
        disp[..., 0] = 3 * np.sin(np.pi * x) * np.sin(np.pi * y) * rng.uniform(-1, 1)
        sitk.WriteImage(image(disp), str(tmp_path / f"w{i}.nii.gz"))
        items.append(f"w{i}.nii.gz")
    data = {
        "images": [f"i{i}.nii.gz" for i in range(n)],
        "labels": [f"l{i}.nii.gz" for i in range(n)],
        "registrations": {
            "warped": {"reference": "i0.nii.gz", "transforms": items},
            "none": {"reference": "i0.nii.gz", "reference_index": 0, "transforms": items[:1] * n},
        },
    }
    path = tmp_path / "manifest.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def slow_case_scores(tmp_path_factory) -> dict:
    """The slow case evaluated in process, without a cache, once for both executors: what a
    killed and restarted run must give (the scores do not depend on where the files are)."""
    return nr.evaluate(slow_case(tmp_path_factory.mktemp("slow")), **KW).to_dict()


@pytest.mark.parametrize("executor", EXECUTORS)
def test_killed_run_restarts_from_cache(tmp_path, executor, slow_case_scores):
    manifest = slow_case(tmp_path)
    cache, out = tmp_path / "cache", tmp_path / "out"
    cmd = [sys.executable, "-m", "itk_nrreval", "evaluate", str(manifest), "--out", str(out)]
    cmd += ["--samples", "2000", "--seed", "5", "--cache", str(cache), "--no-figures", "--quiet"]
    if executor == "dask":
        cmd += ["--scheduler", "local", "--workers", "1"]
    proc = subprocess.Popen(
        cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )

    def per_image_entries() -> int:  # what the run's cache counts count
        kinds = ("resampled", "measures", "estimate")
        return sum(len(list(cache.glob(f"{k}/*/*/entry.json"))) for k in kinds)

    try:
        deadline = time.monotonic() + 300
        while per_image_entries() < 4:
            assert proc.poll() is None, "the run ended before it could be killed"
            assert time.monotonic() < deadline
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its worker processes
        proc.wait()
    done = per_image_entries()
    total = 2 * 12 + 2 * 12 + 12  # both registrations' images resampled and measured, estimates
    assert 4 <= done < total
    assert not (out / "results.json").exists()
    assert main(cmd[3:]) == 0  # the same command again, in this process
    res = json.loads((out / "results.json").read_text())
    assert res["run"]["cache_reused"] >= done
    assert res["run"]["cache_reused"] + res["run"]["cache_computed"] == total
    for name, reg in slow_case_scores["registrations"].items():
        got = res["registrations"][name]
        assert got["specificity"]["value"] == pytest.approx(reg["specificity"]["value"], rel=1e-10)
        for w, v in reg["overlap"].items():
            assert got["overlap"][w] == pytest.approx(v, rel=1e-10)
    assert not list(cache.rglob("*.tmp-*"))  # no half-written entry under a real name


def test_cli_scheduler_errors(tmp_path, capsys):
    manifest = with_mask(tmp_path)
    out = tmp_path / "out"
    assert main(["evaluate", str(manifest), "--out", str(out), "--workers", "2"]) == 2
    assert "--workers needs --scheduler" in capsys.readouterr().err
    cmd = ["evaluate", str(manifest), "--out", str(out), "--scheduler", "local", "--threads", "2"]
    assert main(cmd) == 2
    err = capsys.readouterr().err
    assert "--threads runs tasks in this process: not with --scheduler" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()
    assert main(["evaluate", str(manifest), "--out", str(out), "--scheduler", "nowhere"]) == 2
    err = capsys.readouterr().err
    assert "scheduler: 'nowhere' is neither 'local' nor an address" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()


def test_cli_local_scheduler_reports_cache(tmp_path, capsys):
    manifest = with_mask(tmp_path)
    out = tmp_path / "out"
    args = ["evaluate", str(manifest), "--out", str(out), "--samples", "500", "--no-figures"]
    assert main(args + ["--scheduler", "local", "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "ran on 2 Dask workers; per-image results: 0 reused" in printed
    assert (out / "cache" / "measures").is_dir()
    assert json.loads((out / "results.json").read_text())["run"]["cache_computed"] == 48


def test_cli_keep_resampled(tmp_path):
    """--keep-resampled keeps every registration's resampled images in the cache; without
    it, none is left once the scores are taken, and the numbers are the same."""
    manifest = with_mask(tmp_path)
    base = ["evaluate", str(manifest), "--samples", "500", "--no-figures", "--quiet"]
    assert main([*base, "--out", str(tmp_path / "kept"), "--keep-resampled"]) == 0
    assert main([*base, "--out", str(tmp_path / "default")]) == 0
    kept = list((tmp_path / "kept" / "cache" / "resampled").glob("*/*/entry.json"))
    assert len(kept) == 18
    assert not list((tmp_path / "default" / "cache" / "resampled").glob("*/*/entry.json"))
    scores = [
        json.loads((tmp_path / name / "results.json").read_text())["registrations"]
        for name in ("kept", "default")
    ]
    assert scores[0] == scores[1]


# ----------------------------------------------------------------------------- the cache


def test_cached_arrays_load_as_stored_from_many_threads_at_once(tmp_path):
    """CacheEntry.array reads each .npy header under a lock (CPython 3.11's AST conversion,
    which np.load's header parse uses, is not thread-safe: a full run of the tests once
    failed with "AST constructor recursion depth mismatch"). The race itself could not be
    reproduced on demand; this checks that loading, in memory or memory-mapped, from eight
    threads at once gives back every array as stored: dtype, shape, values, a copy that can
    be written unless memory-mapped."""
    from concurrent.futures import ThreadPoolExecutor

    rng = np.random.default_rng(3)
    arrays = {
        "f32": rng.normal(size=(7, 5)).astype(np.float32),
        "fortran": np.asfortranarray(rng.normal(size=(4, 6))),
        "u4": np.arange(459, dtype=np.uint32),
        "empty": np.zeros((0, 3), np.int16),
        "scalar": np.float64(3.5),
    }
    cache = DiskCache(tmp_path)
    cache.put("k", "cd34", arrays)
    entry = cache.get("k", "cd34")

    def load(_):
        return [(n, m, entry.array(n, mmap=m)) for n in arrays for m in (False, True)] * 20

    with ThreadPoolExecutor(8) as pool:
        for got in pool.map(load, range(32)):
            for name, mmap, a in got:
                want = np.asarray(arrays[name])
                assert a.dtype == want.dtype and a.shape == want.shape, name
                np.testing.assert_array_equal(a, want)
                assert isinstance(a, np.memmap) == mmap and a.flags.writeable == (not mmap)


def test_disk_cache_round_trip_and_corruption(tmp_path):
    cache = DiskCache(tmp_path)
    a = np.arange(10.0)
    entry = cache.put("k", "ab12", {"a": a}, {"x": 1})
    got = cache.get("k", "ab12")
    np.testing.assert_array_equal(got.array("a"), a)
    assert got.meta == {"x": 1} and entry.folder == got.folder
    assert cache.get("k", "other") is None
    cache.put("k", "ab12", {"a": a + 1})  # the same key again: the first entry stays
    np.testing.assert_array_equal(cache.get("k", "ab12").array("a"), a)
    # a temporary folder of a dead process of this host goes; a live process's stays
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = __import__("socket").gethostname()
    (got.folder.parent / f"x.tmp-{host}-{dead.pid}-abc").mkdir()
    (got.folder.parent / f"y.tmp-{host}-{os.getpid()}-abc").mkdir()
    assert cache.remove_stale() == 1
    assert [p.name for p in got.folder.parent.glob("*.tmp-*")] == [
        f"y.tmp-{host}-{os.getpid()}-abc"
    ]
    path = got.folder / "a.npy"
    path.write_bytes(path.read_bytes()[:-8])  # truncated
    assert cache.get("k", "ab12") is None
    assert not got.folder.exists()  # removed, so it will be recomputed


def test_an_entry_another_run_may_read_is_not_removed_under_it(tmp_path):
    """Issue 44, 3: one run's removal of its frame estimates pulled entries from under
    another run sharing the cache (FileNotFoundError on the second). While another run
    uses the cache an entry stays; the run that held off removes it once alone."""
    first, second = DiskCache(tmp_path), DiskCache(tmp_path)
    with first.in_use():
        first.put("frame_disp", "ab12", {"disp": np.arange(6.0)})
        with second.in_use():
            assert second.get("frame_disp", "ab12") is not None  # the second run found it
            first.remove("frame_disp", "ab12")  # the first needs it no more
            entry = second.open("frame_disp", "ab12")  # FileNotFoundError before
            np.testing.assert_array_equal(entry.array("disp"), np.arange(6.0))
        assert first.get("frame_disp", "ab12") is not None  # held off until the run ends
    assert DiskCache(tmp_path).get("frame_disp", "ab12") is None
    assert list((tmp_path / ".runs").iterdir()) == []


def test_a_dead_runs_mark_does_not_hold_off_removals(tmp_path):
    """A run killed mid-way leaves its mark unlocked: it neither holds off removals nor
    stays."""
    cache = DiskCache(tmp_path)
    (tmp_path / ".runs").mkdir()
    (tmp_path / ".runs" / "otherhost-123-abc").write_text("")  # nobody holds its lock
    with cache.in_use():
        cache.put("estimate", "cd34", {"disp": np.zeros(3)})
        cache.remove("estimate", "cd34")
        assert cache.get("estimate", "cd34") is None
    assert list((tmp_path / ".runs").iterdir()) == []


@settings(max_examples=40, deadline=None)
@given(
    dtype=st.sampled_from(["bool", "uint8", "uint16", "int32", "uint32", "float32", "float64"]),
    shape=st.lists(st.integers(0, 7), min_size=0, max_size=3),
    order=st.sampled_from(["C", "F", "strided"]),
    seed=st.integers(0, 2**16),
)
def test_cache_checksum_from_memory_is_the_files(tmp_path_factory, dtype, shape, order, seed):
    """An entry's CRC-32 is taken from the header read back and the array in memory; it
    must be the CRC-32 of the file's bytes (what reading the entry checks), for any dtype
    and memory layout, and the array must read back as written."""
    from itk_nrreval.io._cache import _file_crc32, _save_array

    rng = np.random.default_rng(seed)
    a = (rng.random((*shape, 2)) * 300).astype(dtype)[..., 0]
    if order == "F":
        a = np.asfortranarray(a)
    elif order == "strided" and a.ndim:
        a = a[::2]
    path = tmp_path_factory.mktemp("crc") / "a.npy"
    assert _save_array(path, a) == _file_crc32(path)
    assert zlib.crc32(path.read_bytes()) == int(_file_crc32(path).split(":")[1], 16)
    back = np.load(path)
    assert back.dtype == a.dtype and back.shape == a.shape
    np.testing.assert_array_equal(back, a)


def test_a_flipped_bit_of_the_same_size_is_caught(tmp_path):
    cache = DiskCache(tmp_path)
    a = np.random.default_rng(1).random(1000)
    entry = cache.put("k", "cd34", {"a": a})
    path = entry.folder / "a.npy"
    raw = bytearray(path.read_bytes())
    raw[-3000] ^= 0x10  # one bit of one value: same size, still a valid .npy
    path.write_bytes(bytes(raw))
    assert cache.get("k", "cd34") is None and not entry.folder.exists()


def test_digest_follows_file_content_not_name(tmp_path):
    p, q = tmp_path / "p.txt", tmp_path / "q.txt"
    p.write_text("one")
    q.write_text("one")
    assert digest_of([p, 1]) == digest_of([q, 1]) != digest_of([p, 2])
    before = digest_of({"file": p, "grid": (1.0, 2.0)})
    p.write_text("two")
    assert digest_of({"file": p, "grid": (1.0, 2.0)}) != before
    t = sitk.TranslationTransform(2, (1.0, 0.0))
    assert digest_of(t) == digest_of(sitk.TranslationTransform(2, (1.0, 0.0)))
    assert digest_of(t) != digest_of(sitk.TranslationTransform(2, (1.0, 1e-9)))


def test_progress_bars_on_stderr_unless_quiet(tmp_path, capsys):
    manifest = with_mask(tmp_path)
    args = ["evaluate", str(manifest), "--samples", "500", "--no-figures"]
    assert main(args + ["--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err
    for step in ("resampling", "model", "specificity", "confidence"):
        assert step in err, step
    assert main(args + ["--out", str(tmp_path / "b"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "resampling" not in captured.err and "specificity" not in captured.err
    assert "| truth |" in captured.out  # results still printed


def test_mean_frame_is_added_up_in_image_order_whatever_order_the_estimates_arrive(tmp_path):
    """Issue 30: F is added up from the estimates as their tasks finish, each removed once
    added, so that a registration's N float32 estimates (3.9 GB at 1 mm, N = 36) are not
    all on disk at once; in image order, so that the bits do not depend on the timing."""
    from itk_nrreval._pipeline import _common_frame
    from itk_nrreval.io._cache import DiskCache

    rng = np.random.default_rng(8)
    ests = [
        rng.normal(scale=10 ** rng.uniform(-3, 2), size=(5, 6, 7, 3)).astype(np.float32)
        for _ in range(6)
    ]
    keys = [f"k{i}" for i in range(6)]
    disk = DiskCache(tmp_path)
    expected = np.zeros((5, 6, 7, 3))
    for e in ests:
        expected += e
    expected /= len(ests)
    for order, left in (
        ([0, 1, 2, 3, 4, 5], [5, 4, 3, 2, 1, 0]),
        ([5, 3, 1, 0, 2, 4], [6, 6, 6, 4, 2, 0]),
    ):
        for k, e in zip(keys, ests, strict=True):
            disk.put("estimate", k, {"disp": e})
        mean = _common_frame.MeanOfEstimates(disk, keys)
        on_disk = []
        for i in order:
            mean.arrived(i)
            on_disk.append(sum(disk.get("estimate", k) is not None for k in keys))
        assert on_disk == left
        np.testing.assert_array_equal(mean.result(), expected)
    # two images with the same inputs share one entry: it stays until both are added
    disk.put("estimate", "k0", {"disp": ests[0]})
    twice = _common_frame.MeanOfEstimates(disk, ["k0", "k0"])
    twice.arrived(1)
    twice.arrived(0)
    np.testing.assert_array_equal(twice.result(), ests[0].astype(np.float64))
    assert disk.get("estimate", "k0") is None
    with pytest.raises(RuntimeError, match="1 of 6 estimates arrived"):
        disk.put("estimate", keys[0], {"disp": ests[0]})
        early = _common_frame.MeanOfEstimates(disk, keys)
        early.arrived(0)
        early.result()


@pytest.mark.parametrize("shape", [(7, 9, 11, 3), (13, 17, 2)])
@pytest.mark.parametrize("scale", [1e-3, 1.0, 80.0])
def test_frame_estimates_are_stored_within_half_a_16_bit_step(tmp_path, shape, scale):
    """Issue 30: a registration's N frame estimates are the largest thing the cache holds at
    once; stored in 65535 steps per component, each value comes back within half a step,
    (max - min) / 131070, the extremes exactly or within rounding, a constant component
    exactly; a field that is not finite everywhere is stored as float32."""
    from itk_nrreval._pipeline import _common_frame
    from itk_nrreval.io._cache import DiskCache
    from itk_nrreval.io.frame import from_steps, in_steps

    rng = np.random.default_rng(3)
    disp = rng.normal(scale=scale, size=shape) + rng.normal(scale=10 * scale, size=shape[-1])
    disp[..., -1] = 0.25 * scale  # a constant component
    disk = DiskCache(tmp_path)
    disk.put("estimate", "a", _common_frame._stored_estimate(disp))
    entry = disk.get("estimate", "a")
    assert entry.array("disp").dtype == np.uint16 and entry.array("disp").shape == shape
    back = _common_frame._estimate_values(entry)
    assert back.dtype == np.float64 and back.shape == shape
    flat, got = disp.reshape(-1, shape[-1]), back.reshape(-1, shape[-1])
    half_step = (flat.max(axis=0) - flat.min(axis=0)) / 131070
    rounding = 4 * np.finfo(float).eps * np.abs(flat).max(axis=0)
    assert np.all(np.abs(got - flat).max(axis=0) <= half_step + rounding)
    assert np.all(half_step[:-1] > 0) and np.all(got[:, -1] == 0.25 * scale)
    np.testing.assert_array_equal(got.min(axis=0), flat.min(axis=0))
    np.testing.assert_allclose(got.max(axis=0), flat.max(axis=0), rtol=0, atol=rounding.max())
    q8, low8, step8 = in_steps(disp, levels=255)
    assert q8.dtype == np.uint8
    err8 = np.abs(from_steps(q8, low8, step8) - disp).reshape(-1, shape[-1]).max(axis=0)
    assert np.all(err8 <= half_step * 65535 / 255 + rounding)
    disp.reshape(-1)[5] = np.nan
    assert in_steps(disp) is None
    disk.put("estimate", "b", _common_frame._stored_estimate(disp))
    entry = disk.get("estimate", "b")
    assert entry.array("disp").dtype == np.float32
    np.testing.assert_array_equal(_common_frame._estimate_values(entry), disp.astype(np.float32))


def test_float32_cache_entries_give_the_float64_scores(tmp_path, monkeypatch):
    # Issue 30: resampled images, the frames F and the estimates they are added up from are
    # cached as float32 (half the bytes); the estimates for the spread in 16-bit steps (a
    # quarter): each component within half a step, (max - min) / 131070, of its value.
    # The reductions add up in float64, so every score and frame spread stays within 1e-5
    # (relative) of float64 entries', and the deformation measures, which never read the
    # entries, are the same.
    from itk_nrreval._pipeline import _common_frame, _image_tasks

    data = make_case(tmp_path)
    manifest = tmp_path / "manifest.yaml"
    manifest.write_text(yaml.safe_dump(data, sort_keys=False))
    kept = dict(keep_resampled=True)
    single = nr.evaluate(manifest, execution=nr.Execution(cache=tmp_path / "cache32", **kept), **KW)
    monkeypatch.setattr(_image_tasks, "_STORED_IMAGE", np.float64)
    monkeypatch.setattr(_common_frame, "_STORED_ESTIMATE", np.float64)
    monkeypatch.setattr(_common_frame, "_STORED_FRAME", np.float64)
    double = nr.evaluate(manifest, execution=nr.Execution(cache=tmp_path / "cache64", **kept), **KW)
    for cache, dtype in (("cache32", np.float32), ("cache64", np.float64)):
        # (the frame estimates are removed once F and its spread are kept)
        for kind, name in (("resampled", "image.npy"), ("frame", "disp.npy")):
            entries = list((tmp_path / cache / kind).rglob(name))
            assert entries
            assert {np.load(p, mmap_mode="r").dtype for p in entries} == {np.dtype(dtype)}
    assert list(single.scores) == list(double.scores)
    for name, s64 in double.scores.items():
        s32 = single.scores[name]
        for key, v64 in s64.measures().items():
            assert s32.measures()[key] == pytest.approx(v64, rel=1e-5, abs=1e-9), (name, key)
        assert s32.plausibility == s64.plausibility
        # each distance |F_i - F| moves by at most the length of half a step per component;
        # a step is an estimate's range over 65535, at most F's widest range plus twice
        # the farthest estimate's distance from F
        bound = 0.0
        if s64.frame.method == "mean":
            f = sitk.GetArrayFromImage(s64.frame.transform.GetDisplacementField())
            f = f.reshape(-1, f.shape[-1])
            widest = float((f.max(axis=0) - f.min(axis=0)).max()) + 2 * s64.frame.spread_max_mm
            bound = np.sqrt(f.shape[1]) * widest / (2 * 65535)
        for spread in ("spread_mean_mm", "spread_max_mm"):
            value = getattr(s64.frame, spread)
            assert abs(getattr(s32.frame, spread) - value) <= bound + 1e-5 * abs(value)
        scale = np.abs(double.mean_images[name]).max()  # near-zero voxels: absolute error
        np.testing.assert_allclose(
            single.mean_images[name], double.mean_images[name], rtol=1e-6, atol=1e-6 * scale
        )
