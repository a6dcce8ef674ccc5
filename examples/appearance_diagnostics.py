"""The paper's Table 1 on your registrations: Voronoi cells of full appearance-model samples.

Usage::

    python examples/appearance_diagnostics.py [MANIFEST --registration NAME ...]
        [--samples M] [--out DIR]

Without a manifest, a 2D phantom population of 12 subjects is generated (``nrreval synth``,
with its true transforms as registration ``truth``) and registered with ``nrreval register``:
``affine``, ``fluid`` (demons), ``groupwise``, and ``pairwise`` to the near-mean (``pair1``)
and far-from-mean (``pair2``) subjects -- about 5 minutes on 2 cores. Each registration's
full appearance model is sampled M times (default 1,000 as in the paper) and the samples are
assigned to the nearest raw and projected training image
(:func:`itk_nrreval.appearance_diagnostics`); the tables and the figure
(``appearance_table1.md``, ``appearance_cells.png``, as in docs/results.md) go to ``DIR``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from _output import add_out_option, output_folder

import itk_nrreval as nr
from itk_nrreval.cli import main as nrreval
from itk_nrreval.cli.diagnose import table1_markdown, write_reports

#: name -> extra ``nrreval register`` arguments (the paper's five methods and the truth)
REGISTRATIONS = {
    "affine": ["--method", "affine"],
    "fluid": ["--method", "fluid"],
    "groupwise": ["--method", "groupwise"],
    "pair1": ["--method", "pairwise", "--reference-choice", "near-mean"],
    "pair2": ["--method", "pairwise", "--reference-choice", "far-from-mean"],
}


def make_demo(folder: Path, *, n_images: int = 12, seed: int = 1) -> Path:
    """Generate a 2D phantom population and register it; return the manifest path."""
    manifest = folder / "manifest.yaml"
    args = ["synth", "--kind", "phantom", "--dim", "2", "--n", str(n_images)]
    if nrreval([*args, "--seed", str(seed), "--out", str(folder)]) != 0:
        raise SystemExit("nrreval synth failed")
    images = [str(p) for p in nr.load_manifest(manifest).images]
    for name, extra in REGISTRATIONS.items():
        code = nrreval(
            ["register", "--images", *images, *extra, "--name", name, "--out",
             str(folder / f"reg_{name}"), "--manifest", str(manifest), "--no-progress"]
        )  # fmt: skip
        if code != 0:
            print(f"registration {name} failed; continuing without it")
    return manifest


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("manifest", nargs="?", help="a manifest (default: generate a demo)")
    parser.add_argument("--registration", action="append", metavar="NAME")
    parser.add_argument("--samples", type=int, default=1000, metavar="M")
    parser.add_argument("--seed", type=int, default=0, metavar="S")
    add_out_option(parser)
    args = parser.parse_args()
    with output_folder(args.out, prefix="nrreval-appearance-") as out:
        run(args, out)


def run(args: argparse.Namespace, out: Path) -> None:
    source = Path(args.manifest) if args.manifest else make_demo(out / "data")
    manifest = nr.load_manifest(source)
    names = args.registration or list(manifest.names)
    results = [
        nr.appearance_diagnostics(
            manifest, registration=name, n_samples=args.samples, seed=args.seed
        )
        for name in names
    ]
    paths = write_reports(results, out, images=[str(p) for p in manifest.images])
    print(table1_markdown(results))
    print("written:", ", ".join(str(p) for p in paths))


if __name__ == "__main__":
    main()
