"""itk-elastix in a worker process: the parent side (:class:`ElastixWorker`) and the loop.

itk-elastix costs about 10 s and 1 GB to load and can take its process down (segfaults with
some thread settings), so it never runs in the caller's process. The worker reads one JSON
request per line on stdin and answers one JSON line on a private copy of stdout (its real
stdout and stderr go to a log file, so elastix chatter cannot corrupt the protocol). It runs
in a temporary working directory, where elastix leaves its files. A worker that dies is
reported as :class:`EngineError` with its exit status and the end of its log.

Requests
--------
``{"op": "bspline", "fixed": path, "moving": path, "initial": path or null, "levels": int,
"grid_spacing": float, "parameters": {key: [str, ...]}, "bspline": path, "result": path}``
registers `moving` to `fixed` with elastix's default B-spline map for `levels` and
`grid_spacing` (mm), updated with `parameters`, starting from the ITK transform file
`initial`; writes the final B-spline's parameter map entries (JSON; the parent rebuilds it
as a SimpleITK ``BSplineTransform``) and elastix's result image. Transformix deformation
fields are not used: in one long-lived process they came back with garbage values after a
few dozen jobs (seen with itk-elastix 0.25.4).
``{"op": "stack", "stack": path, "levels": int, "grid_spacing": float, "parameters":
{key: [str, ...]}, "bspline": path, "result": path}`` registers the 2D images stacked along
the last axis of `stack` groupwise (elastix's ``VarianceOverLastDimensionMetric`` and
``BSplineStackTransform``; the grid spacing schedule of elastix's default B-spline map for
`levels` and `grid_spacing`, updated with `parameters`); writes the stack transform's
parameter map entries (JSON; the parent rebuilds one 2D B-spline per image) and elastix's
registered stack.
Answer ``{"ok": true}`` or ``{"ok": false, "error": str}``.
``{"op": "abort"}`` makes the worker abort (SIGABRT), to test how a crash is reported.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import SimpleITK as sitk

from ..._errors import InputError
from ...io._elastix_files import bspline_from_parameter_map
from ._common import EngineError

__all__ = ["ElastixWorker", "elastix_available", "elastix_worker_for"]


class ElastixWorker:
    """A running itk-elastix worker process; use as a context manager, or :meth:`close` it.

    Requests are served one at a time (elastix multithreads each registration itself).

    Raises
    ------
    InputError
        itk-elastix is not installed.
    """

    def __init__(self) -> None:
        if not elastix_available():
            raise InputError(
                "itk-elastix is not installed: pip install itk-elastix (or use --engine simpleitk)"
            )
        self.directory = Path(tempfile.mkdtemp(prefix="nrreval-elastix-"))
        self._log_path = self.directory / "worker.log"
        self._log = open(self._log_path, "wb")  # noqa: SIM115 - kept for the worker's lifetime
        self.process = subprocess.Popen(
            [sys.executable, "-m", "itk_nrreval.experiments.registration._elastix_worker"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
            cwd=self.directory,
            env={
                **os.environ,
                "PYTHONPATH": _package_root() + os.pathsep + os.environ.get("PYTHONPATH", ""),
            },
            text=True,
        )
        self._count = 0

    def __enter__(self) -> ElastixWorker:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def alive(self) -> bool:
        return self.process.poll() is None

    def request(self, message: dict, *, what: str) -> dict:
        """Send one request and wait for its answer; `what` names the job in error messages."""
        if not self.alive:
            raise EngineError(self._death(what))
        try:
            self.process.stdin.write(json.dumps(message) + "\n")
            self.process.stdin.flush()
            line = self.process.stdout.readline()
        except (BrokenPipeError, OSError):
            line = ""
        if not line:
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                pass
            raise EngineError(self._death(what))
        answer = json.loads(line)
        if not answer.get("ok"):
            raise EngineError(f"elastix failed on {what}: {answer.get('error', 'unknown error')}")
        return answer

    def bspline(
        self,
        fixed: sitk.Image,
        moving: sitk.Image,
        *,
        initial: sitk.Transform | None,
        levels: int,
        grid_spacing: float,
        parameters: dict[str, list[str]],
        what: str = "an image",
    ) -> tuple[sitk.Transform, sitk.Image]:
        """B-spline registration of `moving` to `fixed` after `initial` (fixed -> moving).

        Returns
        -------
        transform : sitk.Transform
            The whole transform fixed -> moving: ``CompositeTransform([B, initial])``, i.e.
            ``B(initial(p))`` as elastix composes an initial transform, or ``B`` alone.
        result : sitk.Image
            elastix's own resampling of `moving` on `fixed`'s grid.
        """
        with self._job() as job:
            _write_bare(fixed, job / "fixed.mha")
            _write_bare(moving, job / "moving.mha")
            init = None
            if initial is not None:
                init = str(job / "initial.tfm")
                sitk.WriteTransform(initial, init)
            request = {
                "op": "bspline",
                "fixed": str(job / "fixed.mha"),
                "moving": str(job / "moving.mha"),
                "initial": init,
                "levels": int(levels),
                "grid_spacing": float(grid_spacing),
                "parameters": parameters,
                "bspline": str(job / "bspline.json"),
                "result": str(job / "result.mha"),
            }
            self._request_retrying(request, what=what)
            bspline = _bspline_transform(json.loads((job / "bspline.json").read_text()))
            transform = bspline if initial is None else sitk.CompositeTransform([bspline, initial])
            result = sitk.Cast(sitk.ReadImage(str(job / "result.mha")), sitk.sitkFloat32)
            result.CopyInformation(fixed)
            return transform, result

    def stack(
        self,
        stack: sitk.Image,
        *,
        levels: int,
        grid_spacing: float,
        parameters: dict[str, list[str]],
        what: str = "the stack",
    ) -> tuple[list[sitk.BSplineTransform], sitk.Image]:
        """Groupwise B-spline registration of the 2D slices of a 3D `stack` (last axis: image).

        Returns
        -------
        bsplines : list of sitk.BSplineTransform, one per slice
            Slice ``i``'s 2D transform, frame point -> point of the slice's image (elastix's
            ``BSplineStackTransform`` sub-transform ``i``).
        result : sitk.Image
            elastix's own registered stack (3D, `stack`'s grid).
        """
        if stack.GetDimension() != 3:
            raise InputError("the elastix stack registration needs a 3D stack of 2D images")
        with self._job() as job:
            _write_bare(stack, job / "stack.mha")
            request = {
                "op": "stack",
                "stack": str(job / "stack.mha"),
                "levels": int(levels),
                "grid_spacing": float(grid_spacing),
                "parameters": parameters,
                "bspline": str(job / "bspline.json"),
                "result": str(job / "result.mha"),
            }
            self._request_retrying(request, what=what)
            bsplines = _stack_bsplines(json.loads((job / "bspline.json").read_text()))
            if len(bsplines) != stack.GetSize()[2]:
                raise EngineError(
                    f"elastix returned {len(bsplines)} sub-transforms for "
                    f"{stack.GetSize()[2]} images"
                )
            result = sitk.Cast(sitk.ReadImage(str(job / "result.mha")), sitk.sitkFloat32)
            result.CopyInformation(stack)
            return bsplines, result

    @contextlib.contextmanager
    def _job(self) -> Iterator[Path]:
        """A fresh folder for one request's files, removed afterwards."""
        self._count += 1
        job = self.directory / f"job{self._count:04d}"
        job.mkdir()
        try:
            yield job
        finally:
            shutil.rmtree(job, ignore_errors=True)

    def _request_retrying(self, request: dict, *, what: str) -> dict:
        """:meth:`request`, once more with a new RandomSeed if elastix itself failed.

        elastix's stochastic optimiser occasionally stops with "Error in metric" (too many
        samples outside the moving image); a fresh sample set usually succeeds. A dead
        worker, or a second failure, is reported.
        """
        try:
            return self.request(request, what=what)
        except EngineError:
            if not self.alive:
                raise
            parameters = request["parameters"]
            seed = int(parameters.get("RandomSeed", ["0"])[0]) + 7919
            return self.request(
                {**request, "parameters": {**parameters, "RandomSeed": [str(seed)]}}, what=what
            )

    def _death(self, what: str) -> str:
        code = self.process.returncode
        how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        self._log.flush()
        tail = ""
        try:
            lines = [
                ln for ln in self._log_path.read_text(errors="replace").splitlines() if ln.strip()
            ]
            tail = " | ".join(lines[-3:])[-300:]
        except OSError:
            pass
        return f"the elastix worker process died ({how}) while registering {what}" + (
            f"; its last output: {tail}" if tail else ""
        )

    def close(self) -> None:
        """Stop the worker and remove its working directory."""
        if self.alive:
            try:
                self.process.stdin.close()
                self.process.wait(timeout=10)
            except (OSError, subprocess.TimeoutExpired):
                self.process.kill()
                self.process.wait()
        for stream in (self.process.stdout, self.process.stdin):
            if stream is not None and not stream.closed:
                try:
                    stream.close()
                except OSError:
                    pass
        self._log.close()
        shutil.rmtree(self.directory, ignore_errors=True)


@contextlib.contextmanager
def elastix_worker_for(
    given: ElastixWorker | None, *, needed: bool = True
) -> Iterator[ElastixWorker | None]:
    """The worker a registration uses: `given`, else one started for the block.

    A worker started here is stopped when the block ends, also when it raises; `given` is
    left running for the caller to reuse.

    Parameters
    ----------
    given : ElastixWorker or None
        The caller's running worker.
    needed : bool, keyword-only
        False: start none (the registration runs no elastix job); yields `given`, maybe None.
    """
    if given is not None or not needed:
        yield given
        return
    with ElastixWorker() as started:
        yield started


def _bspline_transform(pm: dict[str, list[str]]) -> sitk.BSplineTransform:
    """elastix's B-spline parameter map as a SimpleITK transform
    (:func:`itk_nrreval.io._elastix_files.bspline_from_parameter_map`)."""
    if pm.get("Transform", [""])[0] not in ("BSplineTransform", "RecursiveBSplineTransform"):
        raise EngineError(f"elastix returned a {pm.get('Transform')} transform, not a B-spline")
    try:
        return bspline_from_parameter_map(pm)
    except ValueError as exc:
        raise EngineError(f"elastix returned {exc}") from None


def _stack_bsplines(pm: dict[str, list[str]]) -> list[sitk.BSplineTransform]:
    """elastix's ``BSplineStackTransform`` parameter map as one SimpleITK B-spline per slice.

    The map's GridSize, GridOrigin, GridSpacing and GridDirection describe every sub-transform
    (the reduced, 2D grid); TransformParameters holds the sub-transforms one after the other,
    each laid out as a plain B-spline's (all x coefficients, then all y). Checked against
    elastix's own registered stack in the tests.
    """
    if pm.get("Transform", [""])[0] != "BSplineStackTransform":
        raise EngineError(
            f"elastix returned a {pm.get('Transform')} transform, not a B-spline stack"
        )
    n = int(pm["NumberOfSubTransforms"][0])
    params = [float(v) for v in pm["TransformParameters"]]
    if n < 1 or len(params) % n:
        raise EngineError(f"elastix returned {len(params)} parameters for {n} sub-transforms")
    size = len(params) // n
    sub = {
        k: pm[k] for k in ("GridSize", "GridIndex", "GridOrigin", "GridSpacing", "GridDirection")
    }
    order = pm.get("BSplineTransformSplineOrder", ["3"])
    out = []
    for i in range(n):
        chunk = [str(v) for v in params[i * size : (i + 1) * size]]
        out.append(
            _bspline_transform(
                {
                    **sub,
                    "Transform": ["BSplineTransform"],
                    "BSplineTransformSplineOrder": order,
                    "TransformParameters": chunk,
                }
            )
        )
    return out


def elastix_available() -> bool:
    """Whether the itk-elastix package is installed (checked without importing it)."""
    from importlib import metadata  # noqa: PLC0415

    try:
        metadata.version("itk-elastix")
    except metadata.PackageNotFoundError:
        return False
    return True


def _package_root() -> str:
    return str(Path(__file__).resolve().parents[2])


# ---------------------------------------------------------------- worker side


def _bspline_job(itk, req: dict) -> None:
    fixed = itk.imread(req["fixed"], itk.F)
    moving = itk.imread(req["moving"], itk.F)
    po = itk.ParameterObject.New()
    pm = po.GetDefaultParameterMap("bspline", int(req["levels"]), float(req["grid_spacing"]))
    for key, value in req["parameters"].items():
        pm[key] = [str(v) for v in (value if isinstance(value, list) else [value])]
    po.AddParameterMap(pm)
    method = itk.ElastixRegistrationMethod.New(
        fixed, moving, parameter_object=po, log_to_console=False
    )
    if req["initial"]:
        initial = itk.transformread(req["initial"])[0]
        method.SetInitialTransform(initial)
    _run_and_save(itk, method, req)


_BSPLINE_KEYS = ("Transform", "TransformParameters", "GridSize", "GridIndex", "GridSpacing")
_BSPLINE_KEYS += ("GridOrigin", "GridDirection", "BSplineTransformSplineOrder")


def _run_and_save(itk, method, req: dict, *, extra_keys: tuple[str, ...] = ()) -> None:
    """Run `method`, write its result image and its final B-spline's parameter map (JSON).

    The B-spline itself, not a transformix deformation field: transformix fields came back
    with garbage values (up to 1e12 mm) on some jobs. elastix explains failures in its log,
    not in the exception, so the log's error lines become the message.
    """
    folder = Path(req["result"]).parent
    method.SetOutputDirectory(str(folder))
    method.SetLogToFile(True)
    method.SetLogFileName("elastix.log")
    try:
        method.UpdateLargestPossibleRegion()
    except RuntimeError as exc:
        raise RuntimeError(_log_errors(folder / "elastix.log") or str(exc)) from None
    itk.imwrite(method.GetOutput(), req["result"])
    tpo = method.GetTransformParameterObject()
    pm = tpo.GetParameterMap(tpo.GetNumberOfParameterMaps() - 1)
    with open(req["bspline"], "w") as fh:
        json.dump({k: list(pm[k]) for k in _BSPLINE_KEYS + extra_keys if k in pm}, fh)


def _stack_job(itk, req: dict) -> None:
    stack = itk.imread(req["stack"], itk.F)
    po = itk.ParameterObject.New()
    levels = int(req["levels"])
    default = po.GetDefaultParameterMap("bspline", levels, float(req["grid_spacing"]))
    pm = {
        k: list(default[k])
        for k in ("GridSpacingSchedule", "NumberOfResolutions", "AutomaticParameterEstimation")
    }
    for key, value in req["parameters"].items():
        pm[key] = [str(v) for v in (value if isinstance(value, list) else [value])]
    po.AddParameterMap(pm)
    method = itk.ElastixRegistrationMethod.New(
        stack, stack, parameter_object=po, log_to_console=False
    )
    _run_and_save(
        itk, method, req, extra_keys=("NumberOfSubTransforms", "StackOrigin", "StackSpacing")
    )


def _log_errors(log: Path) -> str:
    """The error lines of an elastix log (elastix explains failures there, not in the exception)."""
    try:
        lines = log.read_text(errors="replace").splitlines()
    except OSError:
        return ""
    start = next((k for k, ln in enumerate(lines) if "ERROR" in ln or "Error" in ln), None)
    if start is None:
        return ""
    return " ".join(ln.strip() for ln in lines[start : start + 4] if ln.strip())


def _main() -> None:
    proto = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # elastix / ITK output goes to the log, never into the protocol
    import itk  # noqa: PLC0415

    for line in sys.stdin:
        if not line.strip():
            continue
        req = json.loads(line)
        t0 = time.perf_counter()
        try:
            if req.get("op") == "bspline":
                _bspline_job(itk, req)
            elif req.get("op") == "stack":
                _stack_job(itk, req)
            elif req.get("op") == "abort":  # lets the tests check how a crash is reported
                os.abort()
            else:
                raise ValueError(f"unknown request {req.get('op')!r}")
            answer = {"ok": True, "seconds": time.perf_counter() - t0}
        except Exception as exc:  # noqa: BLE001 - every failure is reported to the parent
            msg = " ".join(str(exc).split())
            answer = {"ok": False, "error": f"{type(exc).__name__}: {msg[-400:]}"}
        proto.write(json.dumps(answer) + "\n")
        proto.flush()


if __name__ == "__main__":
    _main()


def _write_bare(image: sitk.Image, path: Path) -> None:
    """Write `image` without its metadata dictionary (geometry and voxels only).

    Images read from NIfTI carry header fields (``descrip``, ``qto_xyz``, ...) that the
    MetaImage writer cannot store; it says so on stderr, once per field and per image.
    """
    # A new image from the voxels: sitk.Image(image) would share the dictionary, and erasing
    # keys in it erases them in the caller's image too.
    vector = image.GetNumberOfComponentsPerPixel() > 1
    bare = sitk.GetImageFromArray(sitk.GetArrayViewFromImage(image), isVector=vector)
    bare.CopyInformation(image)
    sitk.WriteImage(bare, str(path))
