"""Tune a registration's parameters without ground truth: one registration per setting.

The paper's stated purpose is to "select the best method and tune any parameters" without
ground truth. :func:`sweep` registers the same images once per setting of a grid over one
method's options (for instance the demons smoothing, or the B-spline grid spacing), writes
every registration into one manifest with its setting recorded, evaluates them side by side
(:func:`itk_nrreval.evaluate`, same seed: common random numbers) and recommends a setting
only where the verdict (:mod:`itk_nrreval.measures.verdict`) decides it better than every other
setting and it is not flagged implausible; otherwise it recommends none, says why, and
names the settings the verdict leaves open. When the true transforms are known (generated
data), the true correspondence error and its best setting are reported beside it, so one
can see whether the verdict chose well.

Work is reused: the affine stage is computed once for all settings (and kept on disk), a
setting whose registration is already in the output folder with the same options is not
registered again, and the evaluation's per-image cache lives in ``out/cache``, so
extending a sweep by one value registers and evaluates only that value. (The earlier
settings' scores can still move a little then: the scores of all the registrations compared
are taken on the voxels every image covers under every one of them, and a new setting may
cover less; see :class:`itk_nrreval.Coverage`.)
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import math
import numbers
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from .._errors import InputError
from .._output import (
    check_output_folder,
    claim_output_folder,
    json_number,
    write_json,
    write_text,
)
from ..evaluation import EvaluationResult, Execution, evaluate
from ..io.manifest import add_registration, load_manifest, write_manifest
from ..io.transforms import file_stem
from ..report.sweep import write_sweep

__all__ = ["SweepSetting", "SweepResult", "sweep", "parse_parameter", "SWEEP_OUTPUTS"]

_TRUTH_MEASURE = "true_correspondence_error_mm"


@dataclass(frozen=True)
class SweepSetting:
    """One point of the grid: a registration name and the option values it was run with.

    Attributes
    ----------
    name : str
        The registration's name in the manifest (``method`` and the values, e.g.
        ``fluid_smoothing_mm-2``).
    values : dict of str to value
        The swept options and their values for this registration.
    reused : bool
        Found already registered in the output folder with the same options.
    """

    name: str
    values: dict[str, Any]
    reused: bool = False


@dataclass(frozen=True)
class SweepResult:
    """A parameter sweep and its evaluation.

    Attributes
    ----------
    method : str
        The registration method swept.
    parameters : dict of str to tuple
        Each swept option and its values, in the order given.
    settings : tuple of SweepSetting
        One per registration, in grid order (the last parameter varies fastest).
    manifest : Path
        The manifest with every setting's registration.
    evaluation : EvaluationResult
        The side-by-side evaluation (``evaluation.verdict`` holds the ranking).
    recommended : str or None
        The setting the verdict decides better than every other setting
        (:func:`itk_nrreval.measures.verdict.verdict`: ``verdict.decided``), when it is not flagged
        implausible; None otherwise: then no setting is recommended, and `reason` says why.
        (Recommending the lowest specificity of an open set recommended a setting the
        verdict did not decide for, a flagged one included; issue 44.)
    reason : str
        Why `recommended` is recommended, or why no setting is, in words.
    lowest_specificity : str
        The setting with the lowest specificity among `not_separable`: what specificity
        alone would pick there, not a recommendation.
    not_separable : tuple of str
        The open set: the settings no other setting is decided better than (the verdict's
        ``best``), lowest specificity first. One setting when the verdict decides the best.
    decided : bool
        Whether a setting is recommended (`recommended` is not None).
    truth_error_mm : dict of str to float or None
        The true mean correspondence error per setting (mm; lower is better), when the
        true transforms were given.
    best_by : dict of str to str
        The best setting by each measure: ``specificity``, ``overlap.<weighting>`` (when
        labels exist) and ``true_correspondence_error_mm`` (when known).
    spearman : dict of str to float
        Spearman rank correlation over the settings between specificity and each other
        measure (overlap counted so that 1 means agreement: lower specificity with higher
        overlap); NaN when a measure is constant.
    """

    method: str
    parameters: dict[str, tuple]
    settings: tuple[SweepSetting, ...]
    manifest: Path
    evaluation: EvaluationResult = field(repr=False)
    recommended: str | None
    reason: str
    lowest_specificity: str
    not_separable: tuple[str, ...]
    decided: bool
    truth_error_mm: dict[str, float] | None
    best_by: dict[str, str]
    spearman: dict[str, float]

    def rows(self) -> list[dict[str, Any]]:
        """One flat row per setting: its values, every score, its interval and flags."""
        out = []
        for s in self.settings:
            sc = self.evaluation.scores[s.name]
            row: dict[str, Any] = {"registration": s.name, **s.values}
            for measure, value in sc.measures().items():
                row[measure] = json_number(value)
                iv = sc.intervals.get(measure)
                row[f"{measure}.ci95"] = iv.to_list() if iv is not None else None
            if self.truth_error_mm is not None:
                row[_TRUTH_MEASURE] = json_number(self.truth_error_mm[s.name])
            row["flags"] = list(sc.flags)
            row["reused"] = s.reused
            out.append(row)
        return out

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "parameters": {k: list(v) for k, v in self.parameters.items()},
            "manifest": str(self.manifest),
            "recommended": self.recommended,
            "reason": self.reason,
            "lowest_specificity": self.lowest_specificity,
            "not_separable": list(self.not_separable),
            "decided": self.decided,
            "best_by": dict(self.best_by),
            "spearman_vs_specificity": {k: json_number(v) for k, v in self.spearman.items()},
            "settings": self.rows(),
        }


def parse_parameter(text: str) -> tuple[str, tuple]:
    """``"NAME=v1,v2,..."`` -> ``(NAME, (v1, v2, ...))``.

    Values are numbers, ``true``/``false``, or words; a value with ``:`` is a tuple
    (``iterations=100:60:40,50:30:20`` gives two values, each a tuple of three levels).

    Raises
    ------
    InputError
        No ``=``, an empty name, or no value.
    """
    name, sep, values = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise InputError(f"--param {text!r}: expected NAME=VALUE[,VALUE...]")
    items = [v.strip() for v in values.split(",") if v.strip()]
    if not items:
        raise InputError(f"--param {text!r}: no value for {name}")
    parsed = []
    for item in items:
        if ":" in item:
            parsed.append(tuple(_scalar(v) for v in item.split(":")))
        else:
            parsed.append(_scalar(item))
    return name, tuple(parsed)


def _scalar(text: str):
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    try:
        return int(low)
    except ValueError:
        pass
    try:
        return float(low)
    except ValueError:
        return text.strip()


def _setting_name(method: str, values: Mapping[str, Any]) -> str:
    def word(v) -> str:
        if isinstance(v, (tuple, list)):
            return ":".join(word(x) for x in v)
        return f"{v:g}" if isinstance(v, float) else str(v)

    return "_".join([method, *(f"{k}-{word(v)}" for k, v in values.items())])


def _grid(parameters: Mapping[str, Sequence]) -> list[dict[str, Any]]:
    names = list(parameters)
    return [
        dict(zip(names, combo, strict=True)) for combo in itertools.product(*parameters.values())
    ]


def _coerce(default, value, name: str):
    """`value` as the type of the option's default (ints stay ints, numbers become floats)."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise InputError(f"--param {name}: expected true or false, got {value!r}")
        return value
    if isinstance(default, numbers.Integral) and isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(default, numbers.Real) and isinstance(value, numbers.Real):
        if isinstance(value, bool):
            raise InputError(f"--param {name}: expected a number, got {value!r}")
        return float(value)
    return value


def _checked(method: str, parameters: Mapping[str, Sequence], engine: str) -> dict[str, tuple]:
    """The swept values as the option types want them; every setting checked, before any work.

    Raises
    ------
    InputError
        A name that is not an option of `method`, a value of the wrong kind, a setting the
        method's options (or `engine`) refuse, or a value given twice.
    """
    defaults = _defaults(method)
    fields = {f.name: getattr(defaults, f.name) for f in dataclasses.fields(defaults)}
    out = {}
    for name, values in parameters.items():
        if name not in fields:
            raise InputError(
                f"--param {name}: not an option of method {method!r} (options: {', '.join(fields)})"
            )
        coerced = tuple(_coerce(fields[name], v, name) for v in values)
        if len(set(map(repr, coerced))) != len(coerced):
            raise InputError(f"--param {name}: a value is given twice ({list(values)})")
        out[name] = coerced
    from .registration import check_engine_options

    for setting in _grid(out):
        try:
            options = dataclasses.replace(defaults, **setting)
            options.check()
            check_engine_options(method, engine, options)
        except InputError as exc:
            shown = ", ".join(f"{k}={v}" for k, v in setting.items())
            raise InputError(f"--param {shown}: {exc}") from None
    return out


def _previous(
    folder: Path,
    *,
    method: str,
    engine: str,
    seed: int,
    images: list[str],
    options,
    reference_choice: str,
) -> dict | None:
    """The registration log in `folder` when it was made with these settings (`options` the
    method's options dataclass), else None (also when a transform it lists is missing)."""
    expected = _json(
        {
            "method": method,
            "engine": engine,
            "seed": seed,
            "images": images,
            "options": dataclasses.asdict(options),
            "reference_choice": reference_choice,
        }
    )
    try:
        found = json.loads((folder / "registration.json").read_text())
    except (OSError, ValueError):
        return None
    if any(found.get(k) != v for k, v in expected.items()):
        return None
    if not all((folder / t).is_file() for t in found.get("transforms", [])):
        return None
    return found


def _write_registration(result, folder: Path, images: Sequence[str]) -> dict:
    """Write a registration into `folder` (transforms named after the images); its log as
    read back (what :func:`_previous` finds on a rerun)."""
    result.write(folder, names=[file_stem(p) for p in images])
    return json.loads((folder / "registration.json").read_text())


SWEEP_OUTPUTS = (
    "registrations",
    "manifest.yaml",
    "identity.tfm",
    "cache",
    "evaluation",
    "sweep.png",
    "report.html",
    "sweep.csv",
    "sweep.json",
)
"""What :func:`sweep` writes into its folder (and may replace on a rerun)."""


def sweep(
    images: Sequence[str | os.PathLike],
    *,
    method: str,
    parameters: Mapping[str, Sequence],
    out: str | os.PathLike,
    labels: Sequence[str | os.PathLike] | None = None,
    mask: str | os.PathLike | None = None,
    engine: str | None = None,
    reference_choice: str = "near-mean",
    truth: Sequence[sitk.Transform] | None = None,
    truth_reference: str | os.PathLike | None = None,
    n_samples: int = 20_000,
    seed: int = 0,
    progress: bool = True,
) -> SweepResult:
    """Register `images` once per setting of a grid over `method`'s options; evaluate all.

    Parameters
    ----------
    images : sequence of path, length n_images >= 4
        The images (files: the manifest refers to them).
    method : {"fluid", "pairwise", "groupwise", "affine"}
    parameters : mapping of str to sequence
        Option name -> values (fields of
        :class:`~itk_nrreval.experiments.registration.FluidOptions`,
        :class:`~itk_nrreval.experiments.registration.BSplineOptions`,
        :class:`~itk_nrreval.experiments.registration.GroupwiseOptions` or
        :class:`~itk_nrreval.experiments.registration.AffineOptions`). Every combination is run.
    out : path
        Folder: ``registrations/<setting>/`` (transforms, reference, log), ``manifest.yaml``
        (every setting), ``cache/`` (the evaluation's per-image cache), ``evaluation/``
        (the evaluation's reports, its ``report.html`` included) and ``sweep.json`` /
        ``sweep.csv`` / ``sweep.png`` / ``report.html`` (the sweep's page: the verdict in
        words, every setting, the figures; :func:`itk_nrreval.report.sweep.sweep_report_html`).
    labels : sequence of path, optional
        Label maps of the images: the overlap is reported beside specificity.
    mask : path, optional
        Evaluate inside this mask (on the grid of the first setting's reference).
    engine : str, optional
        The registration engine (default: the method's first, see
        :func:`~itk_nrreval.experiments.registration.register`).
    reference_choice : {"near-mean", "far-from-mean"}
        The reference of affine / fluid / pairwise, the same for every setting.
    truth : sequence of sitk.Transform, optional
        The true transforms, `truth_reference` points -> image points (e.g. a generated
        population's ``truth`` registration): the true correspondence error of each setting
        is reported beside its scores.
    truth_reference : path, optional
        The reference image of `truth` (where its non-linear pieces are sampled to invert
        them).
    n_samples, seed
        As :func:`itk_nrreval.evaluate` (the seed also seeds the registrations).
    progress : bool
        Progress bars on stderr.

    Returns
    -------
    SweepResult

    Raises
    ------
    InputError
        An unknown option name, a value the method refuses, fewer than 4 images, before
        any registration runs.
    """
    images, engine, parameters = _check_request(images, method, parameters, engine)
    inputs = [*images, *(labels or ()), mask, truth_reference]
    inputs = [p for p in inputs if isinstance(p, (str, os.PathLike))]
    out = claim_output_folder(
        check_output_folder(out, inputs=inputs, option="out", command="sweep"),
        entries=SWEEP_OUTPUTS,
        command="sweep",
    )
    registrations = _Registrations(
        out / "registrations", images, method, engine, seed, reference_choice
    )
    settings, logs = registrations.plan(parameters)
    logs.update(registrations.register_missing(settings, progress=progress))
    manifest = _write_manifest(
        out,
        settings,
        logs,
        method=method,
        engine=engine,
        images=images,
        labels=labels,
        mask=mask,
    )
    evaluation = evaluate(
        manifest,
        n_samples=n_samples,
        seed=seed,
        execution=Execution(cache=out / "cache"),
        progress=progress,
    )
    truth_error = None
    if truth is not None:
        truth_error = _truth_error(evaluation, manifest, truth, truth_reference)
    result = _summarise(method, parameters, settings, manifest, evaluation, truth_error)
    evaluation.write(out / "evaluation")  # figures, report.html, results.*
    _write(result, out)
    return result


def _check_request(
    images: Sequence[str | os.PathLike],
    method: str,
    parameters: Mapping[str, Sequence],
    engine: str | None,
) -> tuple[list[str], str, dict[str, tuple]]:
    """The images as strings, the engine (the method's default for None) and the swept
    values (:func:`_checked`), every setting checked before any work.

    Raises
    ------
    InputError
        An unknown method or engine, no parameter, fewer than 4 images, or a setting
        :func:`_checked` refuses.
    """
    from .registration import ENGINES

    if method not in ENGINES:
        raise InputError(f"--method {method!r}: not one of {', '.join(ENGINES)}")
    if not parameters:
        raise InputError("--param: give at least one option to sweep (NAME=v1,v2,...)")
    images = [str(p) for p in images]
    if len(images) < 4:
        raise InputError(f"--images: a sweep needs at least 4 images, got {len(images)}")
    engine = ENGINES[method][0] if engine is None else engine
    if engine not in ENGINES[method]:
        raise InputError(f"--engine {engine!r}: not one of {', '.join(ENGINES[method])}")
    return images, engine, _checked(method, parameters, engine)


@dataclass(frozen=True)
class _Registrations:
    """The sweep's registrations, one per setting in ``folder/<name>`` (``out/registrations``):
    the same images, method, engine, seed and reference choice, the options varied."""

    folder: Path
    images: list[str]
    method: str
    engine: str
    seed: int
    reference_choice: str

    def plan(
        self, parameters: Mapping[str, tuple]
    ) -> tuple[tuple[SweepSetting, ...], dict[str, dict]]:
        """Every setting of the grid, in grid order, and the logs of those registered already.

        A setting is ``reused`` when ``folder/<name>`` holds its registration made with the
        same method, engine, seed, images, options and reference choice (:func:`_previous`).
        """
        defaults = _defaults(self.method)
        # groupwise registers to its group mean whatever the reference choice; its log says so
        choice = self.reference_choice
        if self.method == "groupwise":
            choice = "group mean (near-mean frame)"
        settings, logs = [], {}
        for values in _grid(parameters):
            name = _setting_name(self.method, values)
            log = _previous(
                self.folder / name,
                method=self.method,
                engine=self.engine,
                seed=self.seed,
                images=self.images,
                options=dataclasses.replace(defaults, **values),
                reference_choice=choice,
            )
            if log is not None:
                logs[name] = log
            settings.append(SweepSetting(name, values, reused=log is not None))
        return tuple(settings), logs

    def register_missing(
        self, settings: Sequence[SweepSetting], *, progress: bool
    ) -> dict[str, dict]:
        """Register every setting not reused into ``folder/<name>``, from the affine stage
        they share (``folder/_affine``, computed once); their logs by name.

        One elastix worker serves every registration of an elastix engine.
        """
        from .registration import register
        from .registration._elastix_worker import elastix_worker_for

        todo = [s for s in settings if not s.reused]
        if not todo:
            return {}
        affine = _affine_stage(
            self.images, self.folder / "_affine", self.reference_choice, self.seed, progress
        )
        logs = {}
        with elastix_worker_for(None, needed=self.engine.startswith("elastix")) as worker:
            for setting in todo:
                result = register(
                    self.images,
                    method=self.method,
                    engine=self.engine,
                    options=setting.values,
                    affine=affine,
                    seed=self.seed,
                    progress=progress,
                    elastix_worker=worker,
                )
                folder = self.folder / setting.name
                logs[setting.name] = _write_registration(result, folder, self.images)
        return logs


def _write_manifest(
    out: Path,
    settings: Sequence[SweepSetting],
    logs: Mapping[str, dict],
    *,
    method: str,
    engine: str,
    images: list[str],
    labels: Sequence[str | os.PathLike] | None,
    mask: str | os.PathLike | None,
) -> Path:
    """``out/manifest.yaml`` (rewritten): every setting's registration with its method,
    engine and values (one family: the verdict reads the description length between them),
    in grid order, the labels and the mask; ``out/identity.tfm`` its frame transforms."""
    manifest = out / "manifest.yaml"
    with contextlib.suppress(FileNotFoundError):
        manifest.unlink()  # rewritten from this grid's registrations only
    identity = out / "identity.tfm"
    dim = sitk.ReadImage(images[0]).GetDimension()
    sitk.WriteTransform(sitk.TranslationTransform(dim), str(identity))
    for i, setting in enumerate(settings):
        log = logs[setting.name]
        folder = out / "registrations" / setting.name
        # Every setting but groupwise registers to the same reference image: F is the identity.
        same_frame = i > 0 and method != "groupwise"
        add_registration(
            manifest,
            setting.name,
            reference=folder / log["reference"],
            transforms=[folder / t for t in log["transforms"]],
            reference_index=log["reference_index"],
            frame_transform=identity if same_frame else None,
            images=images,
            labels=list(labels) if labels is not None else None,
            parameters={"method": method, "engine": engine, **setting.values},
        )
    if mask is not None:
        m = load_manifest(manifest)
        write_manifest(dataclasses.replace(m, mask=Path(mask).absolute()), manifest)
    return manifest


def _defaults(method: str):
    from .registration import AffineOptions, BSplineOptions, FluidOptions, GroupwiseOptions

    return {
        "affine": AffineOptions(),
        "fluid": FluidOptions(),
        "pairwise": BSplineOptions(),
        "groupwise": GroupwiseOptions(),
    }[method]


def _json(value):
    """`value` as it reads back from JSON (tuples become lists), for comparing with logs."""
    return json.loads(json.dumps(value))


def _affine_stage(images, folder: Path, reference_choice: str, seed: int, progress: bool):
    """The affine stage shared by every setting, kept in `folder` and always read from there.

    Reading it back even when just computed makes a setting registered today and one added
    to the sweep later start from the same bytes.
    """
    from ..io.transforms import read_transform
    from .registration import RegistrationResult, register

    log = _previous(
        folder,
        method="affine",
        engine="simpleitk",
        seed=seed,
        images=images,
        options=_defaults("affine"),
        reference_choice=reference_choice,
    )
    if log is None:
        result = register(
            images,
            method="affine",
            reference_choice=reference_choice,
            seed=seed,
            progress=progress,
        )
        log = _write_registration(result, folder, images)
    transforms = tuple(read_transform(folder / t) for t in log["transforms"])
    return RegistrationResult(
        method="affine",
        engine="simpleitk",
        transforms=tuple(sitk.AffineTransform(t) for t in transforms),
        reference=sitk.ReadImage(str(folder / log["reference"]), sitk.sitkFloat32),
        reference_index=log["reference_index"],
        resampled=(),
        settings=log,
    )


def _truth_error(evaluation, manifest, truth, truth_reference) -> dict[str, float]:
    from ..io._images import Geometry, mask_array, read_image
    from ..io.transforms import invert
    from .correspondence import correspondence_error

    grid = None
    if truth_reference is not None:
        grid = Geometry.from_image(read_image(truth_reference, what="truth reference"))
    subject_to_template = [invert(t, grid=grid) for t in truth]
    m = load_manifest(manifest)
    mask = None
    if m.mask is not None:
        ref = read_image(m.registrations[m.common_frame].reference, what="reference image")
        g = Geometry.from_image(ref)
        mask = mask_array(m.mask, shape=g.shape, geometry=g)
    return correspondence_error(evaluation, m, subject_to_template, mask=mask)


def _spearman(a: Sequence[float], b: Sequence[float]) -> float:
    from scipy.stats import spearmanr

    if len(set(a)) < 2 or len(set(b)) < 2:
        return math.nan
    return float(spearmanr(a, b).statistic)


def _summarise(method, parameters, settings, manifest, evaluation, truth_error) -> SweepResult:
    names = [s.name for s in settings]
    values = {n: evaluation.scores[n].measures() for n in names}
    spec = [values[n]["specificity"] for n in names]
    best_by = {"specificity": min(names, key=lambda n: values[n]["specificity"])}
    spearman = {}
    for measure in values[names[0]]:
        if measure.startswith("overlap."):
            ov = [values[n][measure] for n in names]
            best_by[measure] = max(names, key=lambda n: values[n][measure])
            spearman[measure] = _spearman(spec, [-v for v in ov])
    if truth_error is not None:
        best_by[_TRUTH_MEASURE] = min(names, key=lambda n: truth_error[n])
        spearman[_TRUTH_MEASURE] = _spearman(spec, [truth_error[n] for n in names])
    verdict = evaluation.verdict
    recommended, reason = _recommendation(evaluation)
    return SweepResult(
        method=method,
        parameters=dict(parameters),
        settings=settings,
        manifest=manifest,
        evaluation=evaluation,
        recommended=recommended,
        reason=reason,
        lowest_specificity=verdict.best[0],
        not_separable=tuple(verdict.best),
        decided=recommended is not None,
        truth_error_mm=truth_error,
        best_by=best_by,
        spearman=spearman,
    )


def _recommendation(evaluation: EvaluationResult) -> tuple[str | None, str]:
    """The setting to recommend and why, or None and why none.

    Only a setting the verdict decides better than every other setting, one by one, is
    recommended, and never one flagged implausible (a flag is a warning, not a decision,
    but a recommendation is a claim the warning would contradict).
    """
    verdict = evaluation.verdict
    names = list(evaluation.scores)
    top = verdict.best[0]
    if verdict.decided:
        flags = evaluation.scores[top].flags
        if not flags:
            return top, verdict.text[0]
        return None, (
            f"the verdict decides {top} better than every other setting, but {top} is "
            f"flagged implausible ({'; '.join(flags)}): a flagged setting is not recommended"
        )
    if len(verdict.best) > 1:
        among = [p for p in verdict.open_pairs if {p.a, p.b} <= set(verdict.best)]
        why = f" ({among[0].a} and {among[0].b}: {among[0].reason})" if among else ""
        return None, (
            "the verdict decides no setting better than every other: it leaves "
            f"{_join(verdict.best)} open, none decided better than these{why}"
        )
    beaten = {d.worse for d in verdict.decisions if d.better == top}
    undecided = [n for n in names if n != top and n not in beaten]
    return None, (
        f"the verdict decides no setting better than every other: no setting is decided "
        f"better than {top}, but neither is {top} decided better than {_join(undecided)}"
    )


def _join(names: Sequence[str]) -> str:
    names = list(names)
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _csv(result: SweepResult) -> str:
    import csv
    import io

    rows = result.rows()
    columns = list(rows[0])
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([_cell(row.get(c)) for c in columns])
    return buf.getvalue()


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, (list, tuple)):
        return ";".join(_cell(x) for x in v)
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _write(result: SweepResult, out: Path) -> None:
    """``sweep.png`` and ``report.html`` (:func:`itk_nrreval.report.sweep.write_sweep`), then
    ``sweep.csv`` and ``sweep.json``, each under a temporary name renamed when complete."""
    write_sweep(result, out, truth_measure=_TRUTH_MEASURE)
    write_text(out / "sweep.csv", _csv(result))
    write_json(out / "sweep.json", result.to_dict())
