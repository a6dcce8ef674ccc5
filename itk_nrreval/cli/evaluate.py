"""``nrreval evaluate MANIFEST --out DIR`` (or ``DERIV [DERIV ...]``): score registrations side
by side in one frame."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._options import (
    add_quiet_option,
    at_least_one,
    fraction,
    integer,
    positive,
    positive_or_off,
    ratio_or_off,
    samples,
    seed,
)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "evaluate",
        help="rank registrations of the same images by specificity and overlap",
        description="Bring every registration of a manifest into one common frame, resample "
        "the images (and labels), and score each by specificity, generalization and (with "
        "labels) the generalized overlap, ranked side by side like the paper's Table 3.",
    )
    p.add_argument(
        "manifest",
        nargs="+",
        metavar="MANIFEST|DERIV",
        help="a manifest (YAML or JSON), or BIDS derivatives folders (fMRIPrep, sMRIPrep: one "
        "registration each; see `nrreval manifest`)",
    )
    p.add_argument(
        "--space",
        metavar="SPACE",
        help="with DERIV: the template space (e.g. MNI152NLin2009cAsym, or MNI152NLin6Asym:res-2); "
        "default: the one space the transforms go into",
    )
    p.add_argument("--mask", metavar="FILE", help="with DERIV: a mask on the template's grid")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for results and figures")
    p.add_argument(
        "--samples",
        type=samples,
        default=100_000,
        metavar="M",
        help="model samples (default %(default)s; 1e5 works)",
    )
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="sample seed (default 0)")
    p.add_argument(
        "--distance",
        choices=("l1", "l2"),
        default="l1",
        help="parameter-space distance (default %(default)s, the paper's Table 3)",
    )
    p.add_argument(
        "--interpolation",
        choices=("linear", "bspline"),
        default="linear",
        help="intensity interpolation (default %(default)s; labels: see --label-interpolation)",
    )
    p.add_argument(
        "--label-interpolation",
        choices=("linear", "nearest", "gaussian"),
        default="linear",
        help="label memberships in the common frame: one-hot resampled linearly (default), "
        "crisp nearest-neighbour labels, or one-hot smoothed by --label-sigma mm then linear",
    )
    p.add_argument(
        "--label-sigma",
        type=positive,
        metavar="MM",
        help="with --label-interpolation gaussian: the Gaussian's standard deviation (mm)",
    )
    p.add_argument(
        "--save-resampled",
        action="store_true",
        help="also write the resampled images and membership maps (NIfTI) under DIR/resampled "
        "(exported from the cache once the scores are taken)",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    add_quiet_option(p)
    _add_execution_options(p)
    _add_job_options(p)
    _add_confidence_options(p)
    _add_flag_options(p)
    _add_subject_options(p)
    p.set_defaults(func=run)


def _add_execution_options(p) -> None:
    """Where the work runs, and the per-image cache."""
    p.add_argument(
        "--scheduler",
        metavar="local|slurm|pbs|sge|ADDRESS",
        help="run on Dask: 'local' starts a local cluster; 'slurm', 'pbs' or 'sge' submits "
        "worker jobs through dask-jobqueue (see the batch-job options; needs --workers and "
        "--cache); an address (tcp://host:8786) joins a running cluster; the cache folder "
        "must be visible to every worker",
    )
    p.add_argument(
        "--workers",
        type=integer(1),
        metavar="K",
        help="local cluster: K worker processes (default: CPU count); slurm, pbs, sge: K "
        "single-threaded workers, in jobs of --job-cores each (work starts with the first); "
        "address: wait for K workers",
    )
    p.add_argument(
        "--threads",
        type=integer(1),
        metavar="K",
        help="without --scheduler: K tasks at once on threads of this process (default: 2 on "
        "two or more cores); each holds one image's fields",
    )
    p.add_argument(
        "--cache",
        metavar="CACHE",
        help="per-image result cache (default DIR/cache): a rerun, after an interruption or "
        "with more images or registrations, reuses the frames and transforms' measures and "
        "resamples the images again (none with --keep-resampled)",
    )
    p.add_argument(
        "--keep-resampled",
        action="store_true",
        help="keep every registration's resampled images in the cache (about 50 MB per image "
        "and registration at 1 mm) so that a rerun does not resample them; default: one "
        "registration's at a time",
    )


def _add_job_options(p) -> None:
    """What each batch job asks for, with --scheduler slurm, pbs or sge (dask-jobqueue's
    cluster options; what is not given comes from Dask's jobqueue configuration)."""
    j = p.add_argument_group(
        "batch jobs (with --scheduler slurm, pbs or sge)",
        "Worker jobs submitted through dask-jobqueue and cancelled at the end; an option "
        "not given comes from Dask's jobqueue configuration (~/.config/dask/jobqueue.yaml) "
        "where it has one. See docs/large-cohorts.md.",
    )
    j.add_argument(
        "--job-cores",
        type=integer(1),
        metavar="N",
        help="cores per job, each running one single-threaded worker (default 1; SLURM "
        "--cpus-per-task, PBS ncpus)",
    )
    j.add_argument(
        "--job-memory",
        type=_memory,
        metavar="SIZE",
        help="memory per job, shared by its workers, e.g. 8GiB (default 4GiB per core; "
        "SLURM --mem, PBS mem; SGE: the workers' limit only, request it with --job-directive)",
    )
    j.add_argument(
        "--job-walltime",
        type=_walltime,
        metavar="HH:MM:SS",
        help="each job's time limit (default 00:30:00, dask-jobqueue's): give the whole run's "
        "time, a job that ends takes its worker away (SLURM -t, PBS walltime, SGE h_rt)",
    )
    j.add_argument(
        "--job-queue",
        type=_words,
        metavar="NAME",
        help="partition (SLURM -p) or queue (PBS, SGE -q)",
    )
    j.add_argument(
        "--job-directive",
        dest="job_directives",
        type=_words,
        action="append",
        metavar="LINE",
        help="a further job-script header line, without its #SBATCH / #PBS / #$ prefix; "
        "repeatable; write one that starts with - as --job-directive='--account=lab'",
    )


#: The batch-job options, and the attribute each sets.
JOB_OPTIONS = (
    ("--job-cores", "job_cores"),
    ("--job-memory", "job_memory"),
    ("--job-walltime", "job_walltime"),
    ("--job-queue", "job_queue"),
    ("--job-directive", "job_directives"),
)


def _memory(text: str) -> str:
    """An amount of memory as dask-jobqueue reads it (``8GiB``, ``16GB``)."""
    try:
        from .._scaleout import memory_bytes

        memory_bytes(text)
    except ImportError as exc:  # pragma: no cover - the dask extra is part of [all]
        raise argparse.ArgumentTypeError("needs dask (pip install 'itk-nrreval[dask]')") from exc
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"expected an amount of memory like 8GiB or 16GB, got {text!r}"
        ) from exc
    return text


def _walltime(text: str) -> str:
    """A walltime HH:MM:SS."""
    from .._scaleout import check_walltime

    try:
        return check_walltime(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"expected a walltime HH:MM:SS like 02:00:00, got {text!r}"
        ) from exc


def _words(text: str) -> str:
    """A queue's name or a header line: not empty."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a value, got an empty one")
    return text


def _check_scheduler_options(args: argparse.Namespace) -> None:
    """Refuse, before any work, scheduler options that do not go together."""
    from .._errors import InputError
    from .._scaleout import JOB_QUEUES, check_scheduler

    if args.scheduler is not None:
        check_scheduler(args.scheduler, args.workers)
    if args.scheduler is None and args.workers is not None:
        raise InputError("--workers needs --scheduler (local, slurm, pbs, sge or an address)")
    if args.scheduler is not None and args.threads is not None:
        raise InputError("--threads runs tasks in this process: not with --scheduler")
    given = [option for option, dest in JOB_OPTIONS if getattr(args, dest) not in (None, [])]
    if args.scheduler in JOB_QUEUES:
        if args.workers is None:
            raise InputError(
                f"--scheduler {args.scheduler} needs --workers K (how many single-threaded "
                "workers to submit jobs for)"
            )
        if args.cache is None:
            raise InputError(
                f"--scheduler {args.scheduler} needs --cache CACHE: a folder on a filesystem "
                "that every job sees"
            )
    elif given:
        raise InputError(f"{given[0]} goes with --scheduler slurm, pbs or sge")


def _add_confidence_options(p) -> None:
    """Subject-level confidence (jackknife over the subjects)."""
    c = p.add_argument_group("subject-level confidence (jackknife over the subjects)")
    c.add_argument(
        "--no-confidence", action="store_true", help="skip the intervals and comparisons"
    )
    p.add_argument(  # evidence, not confidence: among the command's own options
        "--description-length",
        action="store_true",
        help="also each registration's description length: label-free evidence the verdict "
        "reads between settings of one method (manifest parameters' method and engine)",
    )
    c.add_argument(
        "--confidence-samples",
        type=integer(2),
        metavar="M",
        help="model samples per jackknife replicate (default min(M, 100000))",
    )
    c.add_argument(
        "--resamples",
        type=integer(2),
        metavar="G",
        help="jackknife groups for specificity (default min(N, 50); N: leave one out)",
    )


def _add_flag_options(p) -> None:
    """Plausibility flags of a registration."""
    f = p.add_argument_group(
        "plausibility flags (a warning in the verdict, not a decision against the registration)"
    )
    from ..io.plausibility import Thresholds

    d = Thresholds()
    f.add_argument(
        "--flag-folded-mean",
        type=fraction,
        default=d.folded_mean,
        metavar="F",
        help=f"flag a mean folded fraction above F (default {d.folded_mean:g})",
    )
    f.add_argument(
        "--flag-folded-max",
        type=fraction,
        default=d.folded_max,
        metavar="F",
        help=f"flag one image's folded fraction above F (default {d.folded_max:g})",
    )
    f.add_argument(
        "--flag-sdlogj-ratio",
        type=positive,
        default=d.sdlogj_ratio,
        metavar="R",
        help=f"flag SDlogJ above R x the median of the registrations (default {d.sdlogj_ratio:g})",
    )
    f.add_argument(
        "--flag-sdlogj-floor",
        type=positive,
        default=d.sdlogj_floor,
        metavar="S",
        help=f"... and above S (default {d.sdlogj_floor:g})",
    )
    f.add_argument(
        "--flag-frame-spread",
        type=fraction,
        default=d.frame_spread_fraction,
        metavar="F",
        help="flag a mean frame spread above F x the smallest field-of-view extent "
        f"(default {d.frame_spread_fraction:g})",
    )
    f.add_argument(
        "--no-inverse-consistency",
        action="store_true",
        help="skip the inverse-consistency error (one numerical inversion per image)",
    )


def _add_subject_options(p) -> None:
    """Subject flags: one option per field of SubjectThresholds."""
    from ..io.plausibility import SubjectThresholds

    q = p.add_argument_group(
        "subject flags (which subjects of a registration stand out from its cohort; robust "
        "z-scores over the subjects)"
    )
    for option, field_name, parse, metavar, words in SUBJECT_OPTIONS:
        default = getattr(SubjectThresholds(), field_name)
        q.add_argument(
            option,
            dest=f"subject_{field_name}",
            type=parse,
            default=default,
            metavar=metavar,
            help=f"{words} (default {'off' if default is None else f'{default:g}'})",
        )


#: ``--subject-*`` options: option, SubjectThresholds field, parser, metavar, help.
SUBJECT_OPTIONS = (
    (
        "--subject-z",
        "outlier_z",
        positive,
        "Z",
        "flag a subject whose log distance to the model of the others has z above Z",
    ),
    (
        "--subject-deformation-z",
        "deformation_z",
        positive,
        "Z",
        "flag a subject whose log SDlogJ, non-linear displacement or inverse-consistency "
        "error has z above Z and is above --subject-deformation-ratio x the cohort's median",
    ),
    (
        "--subject-deformation-ratio",
        "deformation_ratio",
        positive,
        "R",
        "see --subject-deformation-z",
    ),
    (
        "--subject-corrected-ratio",
        "corrected_ratio",
        ratio_or_off,
        "R",
        "flag a subject whose bias-corrected distance to the mean of the others (gain and "
        "smooth bias taken away) is above R x the cohort's median; 1.4 was measured on "
        "genuine registrations (docs/subject-qc.md)",
    ),
    (
        "--subject-concern",
        "concern",
        positive_or_off,
        "C",
        "flag a subject whose concern (the weighted mean of its robust z-scores that ranks "
        "the subjects, docs/subject-qc.md) is above C, where its labels were measured",
    ),
    (
        "--subject-concern-without-labels",
        "concern_without_labels",
        positive_or_off,
        "C",
        "the same, for a subject whose labels were not measured (its concern has no overlap term)",
    ),
    (
        "--subject-overlap-z",
        "overlap_z",
        positive,
        "Z",
        "flag a subject whose label overlap with the others has z below -Z and whose "
        "mismatch (1 - overlap) is above --subject-overlap-ratio x the cohort's median",
    ),
    (
        "--subject-overlap-ratio",
        "overlap_ratio",
        positive,
        "R",
        "see --subject-overlap-z",
    ),
    (
        "--subject-folded",
        "folded",
        fraction,
        "F",
        "flag a subject whose transform folds more than F of its voxels",
    ),
    (
        "--subject-off-grid",
        "off_grid_coverage",
        fraction,
        "F",
        "flag, and leave out of every score, a subject covering less of the common grid "
        "than F x the median subject",
    ),
    (
        "--subject-duplicate",
        "duplicate_distance",
        fraction,
        "F",
        "flag two subjects whose resampled images are closer than F x the median pairwise "
        "distance as duplicates",
    ),
    (
        "--subject-affine-only",
        "affine_only_ratio",
        fraction,
        "F",
        "flag a subject whose non-linear displacement is below F x the cohort's median "
        "(stopped early, affine only)",
    ),
    (
        "--subject-scaled-ratio",
        "scaled_ratio",
        positive,
        "R",
        "diagnose scaled displacements when a subject flagged for its deformation moves "
        "more than R x the cohort's median",
    ),
    (
        "--subject-better-fit",
        "better_fit_ratio",
        at_least_one,
        "R",
        "diagnose an inverted transform, or another subject's transform, when the image "
        "through the inverse, or another flagged subject's image through it, is R x closer "
        "to the model of the others",
    ),
)


def run(args: argparse.Namespace) -> int:
    from .._errors import InputError
    from .._output import check_output_folder, staged_folder
    from .._scaleout import JOB_QUEUES, check_job_queue
    from ..evaluation import Execution, evaluate, export_resampled
    from ..report import summary_table

    if (args.label_interpolation == "gaussian") != (args.label_sigma is not None):
        raise InputError(
            "--label-sigma MM goes with --label-interpolation gaussian, and only with it"
        )
    _check_scheduler_options(args)
    manifest = _manifest(args)  # every problem, before DIR is created
    out = check_output_folder(args.out, inputs=manifest.files, command="evaluate")
    cache = Path(args.cache) if args.cache is not None else out / "cache"
    if args.cache is not None:
        check_output_folder(cache, inputs=manifest.files, option="--cache", shared=True)
    if args.scheduler in JOB_QUEUES:
        # the submit command, and a cache that can be written: before any job is submitted
        check_job_queue(args.scheduler, cache=cache, option="--cache")
    execution = Execution(
        scheduler=args.scheduler,
        workers=args.workers,
        threads=args.threads,
        cache=cache,
        # --save-resampled exports them from the cache once the scores are taken
        keep_resampled=args.keep_resampled or args.save_resampled,
        # an option not given: Execution's default (no directive: None, not [])
        **{dest: getattr(args, dest) for _, dest in JOB_OPTIONS if getattr(args, dest)},
    )
    # DIR is claimed and locked for the whole run; everything but the cache is written into a
    # staged copy of it, swapped in when complete (an error or Ctrl-C keeps the previous one)
    with staged_folder(out, command="evaluate") as stage:
        result = evaluate(manifest, **_evaluate_options(args), execution=execution)
        result.write(stage, figures=not args.no_figures)
        if args.save_resampled:
            export_resampled(result, stage / "resampled", cache=cache, keep=args.keep_resampled)
    print(summary_table(result), end="")
    r = result.run
    where = (
        f"on {r['workers']} Dask workers"
        if r["scheduler"]
        else f"in this process ({r['threads']} task{'s' if r['threads'] > 1 else ''} at once)"
    )
    print(
        f"ran {where}; per-image results: {r['cache_reused']} reused from {cache}/, "
        f"{r['cache_computed']} computed"
    )
    print(f"results written to {out}/")
    return 0


def _evaluate_options(args: argparse.Namespace) -> dict:
    """:func:`~itk_nrreval.evaluation.evaluate`'s options from the command line's, but
    `execution`."""
    from ..evaluation import Confidence, Resampling
    from ..io.plausibility import SubjectThresholds, Thresholds

    return dict(
        n_samples=args.samples,
        seed=args.seed,
        distance=args.distance,
        resampling=Resampling(
            interpolation=args.interpolation,
            label_interpolation=args.label_interpolation,
            label_sigma_mm=args.label_sigma,
        ),
        progress=not args.quiet,
        confidence=(
            False
            if args.no_confidence
            else Confidence(samples=args.confidence_samples, resamples=args.resamples)
        ),
        inverse_consistency=not args.no_inverse_consistency,
        description_length=args.description_length,
        thresholds=Thresholds(
            folded_mean=args.flag_folded_mean,
            folded_max=args.flag_folded_max,
            sdlogj_ratio=args.flag_sdlogj_ratio,
            sdlogj_floor=args.flag_sdlogj_floor,
            frame_spread_fraction=args.flag_frame_spread,
        ),
        subject_thresholds=SubjectThresholds(
            **{field: getattr(args, f"subject_{field}") for _, field, *_ in SUBJECT_OPTIONS}
        ),
    )


def _manifest(args: argparse.Namespace):
    """One manifest file, read as it always was; or derivatives folders, read as
    ``nrreval manifest DERIV ...`` reads them."""
    from .._errors import InputError
    from ..io.manifest import load_manifest
    from .manifest import manifest_of

    sources = [Path(s) for s in args.manifest]
    folders = [s.is_dir() for s in sources]
    if all(folders):
        return manifest_of(argparse.Namespace(derivatives=args.manifest, **vars(args)))
    for option in ("space", "mask"):
        if getattr(args, option) is not None:
            raise InputError(f"--{option} goes with derivatives folders, not a manifest")
    if len(sources) > 1:
        file = next(s for s, folder in zip(sources, folders, strict=True) if not folder)
        if not file.exists():
            raise InputError(f"{file}: not found (expected a derivatives folder)")
        raise InputError(
            f"{file}: give one manifest file, or derivatives folders (not a file among several)"
        )
    return load_manifest(args.manifest[0])
