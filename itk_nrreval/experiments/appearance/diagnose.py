"""Appearance-model diagnostics of several registrations, as ``nrreval diagnose`` writes them.

:func:`diagnose` runs :func:`itk_nrreval.appearance_diagnostics` (the paper's Table 1:
Voronoi cell populations of full appearance-model samples) for each named registration of a
manifest -- a file, or a dict whose images and transforms may be objects in memory -- and
returns a :class:`DiagnosticsResult`, whose :meth:`~DiagnosticsResult.write` writes::

    appearance_table1.md     Table 1 layout (raw rows, then projected rows; **0** = empty
                             cell), then empty / near-empty fractions, specificity and
                             representation error per registration and variant
    appearance_table1.csv    one row per registration and variant, one column per image
    appearance_diagnostics.json   every number, the settings and the inputs
    appearance_cells.png     cell-population bars, raw vs projected, one panel per registration

Every file is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..._errors import InputError
from ...io.manifest import Manifest, load_manifest
from ...report.diagnostics import table1_markdown, write_diagnostics
from .model import AppearanceDiagnostics, appearance_diagnostics

__all__ = ["DiagnosticsResult", "diagnose"]


@dataclass(frozen=True)
class DiagnosticsResult:
    """The appearance-model diagnostics of one or more registrations of the same images.

    Attributes
    ----------
    results : tuple of AppearanceDiagnostics
        One per registration, in the order asked for.
    inputs : dict
        The manifest's description (:meth:`Manifest.describe`).
    version : str
        The toolkit version.
    """

    results: tuple[AppearanceDiagnostics, ...]
    inputs: Mapping[str, Any] = field(repr=False)
    version: str = ""

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(r.registration for r in self.results)

    def table_markdown(self) -> str:
        """The Table 1 layout as Markdown
        (:func:`itk_nrreval.report.diagnostics.table1_markdown`)."""
        return table1_markdown(self.results)

    def to_dict(self) -> dict:
        """The content of ``appearance_diagnostics.json``."""
        return {
            "version": self.version,
            "images": list(self.inputs.get("images", ())),
            "inputs": dict(self.inputs),
            "registrations": [r.to_dict() for r in self.results],
        }

    def write(self, out_dir: str | os.PathLike) -> list[Path]:
        """Write the reports ``nrreval diagnose`` writes into `out_dir` (created if needed).

        Returns
        -------
        list of Path
            ``appearance_table1.md``, ``appearance_table1.csv``,
            ``appearance_diagnostics.json`` and ``appearance_cells.png``, each written under
            a temporary name and renamed when complete.
        """
        return write_diagnostics(self, out_dir)


def diagnose(
    manifest: Manifest | Mapping | str | os.PathLike,
    *,
    registrations: Sequence[str] | None = None,
    n_samples: int = 1000,
    seed: int = 0,
    progress: bool = True,
    out: str | os.PathLike | None = None,
) -> DiagnosticsResult:
    """The paper's Table 1 for several registrations of a manifest.

    Parameters
    ----------
    manifest : Manifest, dict or path
        See :mod:`itk_nrreval.io.manifest`; in a dict, images and transforms may be objects in
        memory (SimpleITK, ITK Python, arrays with their grid), mixed with paths.
    registrations : sequence of str, optional
        The registrations to diagnose, in this order (default: every one of the manifest).
    n_samples : int
        M, the model samples per registration (the paper uses 1,000).
    seed : int
        Seed of the model samples (the same for every registration).
    progress : bool
        Progress bars on stderr.
    out : path, optional
        Also write the reports (:meth:`DiagnosticsResult.write`) into this folder.

    Returns
    -------
    DiagnosticsResult

    Raises
    ------
    InputError
        A bad manifest, an unknown registration, an `out` that cannot be a folder.
    ValueError
        `n_samples` or `seed` out of range.
    """
    from ..._output import check_output_folder
    from ..._version import __version__

    if out is not None:
        check_output_folder(out, option="out", command="diagnose")
    m = load_manifest(manifest)  # every problem, before any work
    names = list(dict.fromkeys(registrations if registrations is not None else m.names))
    unknown = [n for n in names if n not in m.registrations]
    if unknown or not names:
        raise InputError(
            f"registrations: {', '.join(map(repr, unknown)) or 'none given'}: not in the "
            f"manifest (have: {', '.join(m.names)})"
        )
    results = tuple(
        appearance_diagnostics(
            m, registration=name, n_samples=n_samples, seed=seed, progress=progress
        )
        for name in names
    )
    result = DiagnosticsResult(results, m.describe(), __version__)
    if out is not None:
        result.write(out)
    return result
