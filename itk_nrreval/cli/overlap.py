"""``nrreval overlap LABELS...``: generalized Tanimoto overlap of a group of label maps."""

from __future__ import annotations

import argparse
import csv
import io
from pathlib import Path

from .._errors import InputError
from .._output import write_json, write_text
from ._options import add_quiet_option

_COLUMNS = ("label", "volume", "complexity", "jaccard", "dice", "target_overlap")


def add_parser(sub) -> None:
    from ..measures.overlap import WEIGHTINGS

    p = sub.add_parser(
        "overlap",
        help="generalized Tanimoto overlap of registered label maps (the ground-truth reference)",
        description="Generalized Tanimoto overlap (Crum et al. 2006, eq. 4 without pair weights) "
        "of N label maps on one grid: integer label images, or one multi-component membership "
        "image per subject (component k is label k, 0 the background, unless the files name "
        "their labels, as those of `nrreval evaluate --save-resampled` do). Higher is better.",
    )
    p.add_argument("labels", nargs="+", metavar="LABELS", help="label maps (NIfTI, MHA, NRRD)")
    p.add_argument(
        "--weighting",
        action="append",
        choices=WEIGHTINGS,
        metavar="W",
        help=f"label weighting, repeatable; one of {', '.join(WEIGHTINGS)} (default: all)",
    )
    p.add_argument("--include-background", action="store_true", help="also evaluate label 0")
    p.add_argument("--mask", help="evaluate only voxels where this image is nonzero")
    p.add_argument(
        "--label-names",
        metavar="FILE",
        help="the labels' names, shown beside the values (a label_name column): a BIDS "
        "dseg.tsv (columns index and name) or a FreeSurfer FreeSurferColorLUT.txt-style table",
    )
    p.add_argument(
        "--table",
        metavar="OUT.csv",
        help="write the per-label table (volume mm^3, complexity mm^-1, Jaccard, Dice, target "
        "overlap, and each chosen weighting's weights normalized to sum 1) to this CSV file",
    )
    p.add_argument("--json", metavar="OUT", help="also write the numbers to this JSON file")
    add_quiet_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .._output import TOOL, check_output_file, json_written_by_nrreval
    from .._version import __version__
    from ..io.label_names import read_label_names
    from ..measures.overlap import WEIGHTINGS, overlap_table

    inputs = [*args.labels, *(p for p in (args.mask,) if p is not None)]
    if args.table:  # before the work, not after it
        check_output_file(args.table, inputs=inputs, option="--table", ours=_our_table)
    if args.json:
        check_output_file(args.json, inputs=inputs, option="--json", ours=json_written_by_nrreval)
    if args.table and args.json and Path(args.table).resolve() == Path(args.json).resolve():
        raise InputError("--table and --json: the same file")

    names = read_label_names(args.label_names) if args.label_names else None
    weightings = list(dict.fromkeys(args.weighting)) if args.weighting else list(WEIGHTINGS)
    table = overlap_table(
        args.labels,
        include_background=args.include_background,
        mask=args.mask,
        progress=not args.quiet,
    )
    values = {w: table.generalized(w) for w in weightings}
    kind = "fuzzy" if table.fuzzy else "crisp"
    print(f"generalized overlap of {table.n_images} {kind} label maps, {len(table.labels)} labels:")
    for w in weightings:
        print(f"  {w:<27s} {values[w]:.6f}")
    rows = _rows(table, weightings, names)
    print()
    print(_format(rows))
    if args.table:
        write_text(args.table, _csv(rows))
    if args.json:
        write_json(
            args.json,
            {
                "tool": TOOL,
                "version": __version__,
                "label_maps": list(args.labels),
                "include_background": args.include_background,
                "mask": args.mask,
                "n_images": table.n_images,
                "fuzzy": table.fuzzy,
                "spacing": list(table.spacing),
                "skipped_labels": list(table.skipped_labels),
                "generalized": values,
                "labels": rows,
            },
        )
    return 0


def _rows(table, weightings, names=None) -> list[dict]:
    rows = [{k: r[k] for k in _COLUMNS} for r in table.rows()]
    if names is not None:  # the name beside the value
        rows = [{"label": r["label"], "label_name": names.get(r["label"], ""), **r} for r in rows]
    for w in weightings:
        alpha = table.weights(w)
        total = alpha.sum()
        for r, a in zip(rows, alpha, strict=True):
            r[f"weight_{w}"] = float(a / total) if total > 0 else float("nan")
    return rows


def _format(rows: list[dict]) -> str:
    names = ("label", "volume", "complexity", "jaccard", "dice", "target")
    widths = (6, 12, 10, 8, 8, 8)
    lines = [" ".join(f"{n:>{w}}" for n, w in zip(names, widths, strict=True))]
    if rows and "label_name" in rows[0]:
        lines[0] += "  name"
    for r in rows:
        lines.append(
            f"{r['label']:>6d} {r['volume']:>12.6g} {r['complexity']:>10.4g} "
            f"{r['jaccard']:>8.4f} {r['dice']:>8.4f} {r['target_overlap']:>8.4f}"
            + (f"  {r['label_name']}" if r.get("label_name") else "")
        )
    return "\n".join(lines)


def _csv(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return out.getvalue()


def _our_table(path: Path) -> bool:
    """Whether `path` is a table this command wrote: its header starts with our columns."""
    try:
        with open(path, encoding="utf-8") as f:
            header = f.readline().rstrip("\n").split(",")
    except (OSError, UnicodeDecodeError):
        return False
    header = [h for h in header if h != "label_name"]  # written with --label-names
    return header[: len(_COLUMNS)] == list(_COLUMNS)
