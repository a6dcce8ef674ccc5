"""``nrreval validate (MANIFEST | --synthetic KIND) --out DIR``: the paper's Section IV."""

from __future__ import annotations

import argparse
from pathlib import Path

from .._errors import InputError
from .._output import atomic_path, write_json, write_text
from ._options import seed


def _floats(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers such as 0,0.5,1, got {text!r}"
        ) from None
    if not values or any(not (v >= 0) for v in values):
        raise argparse.ArgumentTypeError(f"displacements must be numbers >= 0, got {text!r}")
    return values


def add_parser(sub) -> None:
    from ..overlap import WEIGHTINGS
    from ..validation import DEFAULT_DISPLACEMENTS

    p = sub.add_parser(
        "validate",
        help="perturb a registered set with random CPS warps; specificity vs overlap",
        description="The validation experiment of the paper (Section IV): every image of a "
        "registered, labelled set is perturbed by its own random clamped-plate-spline warp of "
        "mean displacement d pixels; the specificity and generalized overlap of each perturbed "
        "set are recorded. Writes validation.csv/.json, validation_fig2.png (specificity vs "
        "overlap) and validation_vs_d.png into --out.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "manifest", nargs="?", metavar="MANIFEST", help="manifest with labels (common frame)"
    )
    src.add_argument(
        "--synthetic",
        choices=("phantom", "mni"),
        metavar="KIND",
        help="generated brain-like data, perfectly registered: phantom or mni",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--n-images", type=int, default=10, metavar="N", help="synthetic N (default 10)")
    p.add_argument(
        "--displacements",
        type=_floats,
        default=list(DEFAULT_DISPLACEMENTS),
        metavar="D,D,...",
        help="mean pixel displacements (default "
        + ",".join(f"{d:g}" for d in DEFAULT_DISPLACEMENTS)
        + ")",
    )
    p.add_argument(
        "--repeats", type=int, default=5, metavar="R", help="perturbations per d (default 5)"
    )
    p.add_argument(
        "--samples",
        type=int,
        default=50_000,
        metavar="M",
        help="specificity samples (default 50000)",
    )
    p.add_argument(
        "--weighting",
        action="append",
        choices=WEIGHTINGS,
        metavar="W",
        help="overlap weighting, repeatable; the first is plotted "
        "(default complexity, inverse_volume)",
    )
    p.add_argument(
        "--knots", type=int, default=25, metavar="K", help="CPS knots per warp (default 25)"
    )
    p.add_argument("--seed", type=seed, default=0, metavar="S")
    p.add_argument("--jobs", type=int, default=2, metavar="J", help="threads (default 2)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .._version import __version__
    from ..validation import manifest_set, synthetic_set, validate

    if args.n_images < 3:
        raise InputError(f"--n-images must be at least 3, got {args.n_images}")
    if args.repeats < 1 or args.samples < 2 or args.knots < 1:
        raise InputError("--repeats and --knots must be >= 1 and --samples >= 2")
    weightings = tuple(args.weighting) if args.weighting else ("complexity", "inverse_volume")
    if args.synthetic:
        images, labels = synthetic_set(args.synthetic, n_images=args.n_images, seed=args.seed)
        source = f"synthetic:{args.synthetic}"
    else:
        images, labels, _ = manifest_set(args.manifest)
        source = str(args.manifest)
    result = validate(
        images,
        labels,
        displacements=args.displacements,
        repeats=args.repeats,
        n_samples=args.samples,
        weightings=weightings,
        n_knots=args.knots,
        seed=args.seed,
        n_jobs=args.jobs,
        progress=not args.no_progress,
        source=source,
    )
    out = Path(args.out)
    write_text(out / "validation.csv", result.to_csv())
    write_json(out / "validation.json", {"version": __version__, **result.to_dict()})
    with atomic_path(out / "validation_fig2.png") as tmp:
        plot_fig2(result, tmp)
    with atomic_path(out / "validation_vs_d.png") as tmp:
        plot_vs_d(result, tmp)
    s = result.summary
    w0 = weightings[0]
    print(f"{len(result.rows)} perturbed sets of {result.n_images} images ({source})")
    print(f"Pearson r (specificity vs {w0} overlap, d >= 0.375) = {s.pearson_r[w0]:.4f}")
    for w in weightings[1:]:
        print(f"Pearson r (specificity vs {w} overlap, d >= 0.375) = {s.pearson_r[w]:.4f}")
    print(f"Spearman (mean specificity vs d, d >= 0.375) = {s.spearman:.4f}")
    print(f"sensitivity = {s.sensitivity:.3g} standard errors per pixel of d")
    print(
        f"wrote {out / 'validation.csv'}, validation.json, validation_fig2.png, validation_vs_d.png"
    )
    return 0


def plot_fig2(result, path, *, weighting: str | None = None) -> None:
    """The paper's Fig. 2: specificity against overlap, coloured by d.

    The grey line is the least-squares fit over ``d >= 0.375``; the dashed line is the
    unperturbed specificity (d = 0). Written to `path` (PNG).
    """
    import matplotlib
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: the process's backend is left alone

    from ..validation import FIT_FROM

    w = weighting or result.weightings[0]
    d = result.column("displacement")
    s = result.column("specificity")
    se = result.column("specificity_stderr")
    o = result.column(f"overlap_{w}")
    fig = Figure(figsize=(6.4, 4.8), dpi=120)
    ax = fig.subplots()
    levels = np.unique(d)
    cmap = matplotlib.colormaps["viridis"].resampled(len(levels))
    for k, v in enumerate(levels):
        sel = d == v
        ax.errorbar(o[sel], s[sel], yerr=se[sel], fmt="o", ms=5, color=cmap(k), label=f"{v:g}")
    fit = d >= FIT_FROM
    if np.unique(d[fit]).size >= 2:
        a, b = np.polyfit(o[fit], s[fit], 1)
        xs = np.linspace(o[fit].min(), o[fit].max(), 2)
        r = result.summary.pearson_r[w]
        ax.plot(
            xs, a * xs + b, color="0.5", lw=2, zorder=0, label=f"fit d>={FIT_FROM:g} (r={r:.3f})"
        )
    if result.summary.unperturbed is not None:
        ax.axhline(result.summary.unperturbed, ls="--", color="k", lw=1, label="d = 0")
    ax.set_xlabel(f"generalized Tanimoto overlap ({w.replace('_', '-')} weighted)")
    ax.set_ylabel(f"specificity (M = {result.n_samples:,})")
    ax.set_title(f"N = {result.n_images} images, {len(result.rows)} perturbed sets")
    ax.legend(title="d (pixels)", fontsize=7, title_fontsize=8, ncol=2, loc="best")
    fig.tight_layout()
    fig.savefig(path, format="png")


def plot_vs_d(result, path) -> None:
    """Specificity and overlap against d: mean over repeats, error bars one SD (PNG)."""
    from matplotlib.figure import Figure

    m = result.means()
    fig = Figure(figsize=(10, 4), dpi=120)
    a1, a2 = fig.subplots(1, 2)
    a1.errorbar(m["displacement"], m["specificity"], yerr=m["specificity_sd"], fmt="o-", capsize=3)
    a1.set_xlabel("mean displacement d (pixels)")
    a1.set_ylabel("specificity")
    a1.set_title("specificity (error bars: SD over repeats)")
    for w in result.weightings:
        a2.errorbar(
            m["displacement"],
            m[f"overlap_{w}"],
            yerr=m[f"overlap_{w}_sd"],
            fmt="o-",
            capsize=3,
            label=w,
        )
    a2.set_xlabel("mean displacement d (pixels)")
    a2.set_ylabel("generalized Tanimoto overlap")
    a2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, format="png")
