"""Writing an :class:`~itk_nrreval.evaluation.EvaluationResult`: figures, ``report.html``,
then ``results.json``, ``results.csv``, ``metrics.csv``, ``summary.md`` and ``subjects.csv``.

Every file is written under a temporary name and renamed when complete; figures are written
first, then ``report.html``, and the ``results.*`` files last, so an interrupted run leaves no
partial ``results.*``.
"""

from __future__ import annotations

import os
from pathlib import Path

from .._output import atomic_path, claim_entries, write_text
from .evaluation_figures import figure_pngs
from .evaluation_page import report_html
from .evaluation_text import (
    metrics_csv,
    results_csv,
    results_json,
    subjects_csv,
    summary_table,
)

__all__ = ["write_evaluation"]


def write_evaluation(result, out: str | os.PathLike, *, figures: bool = True) -> list[Path]:
    """Write the figures, then ``report.html``, then ``results.json``, ``results.csv``,
    ``metrics.csv`` (the numbers registration papers report:
    :func:`~.evaluation_text.metrics_csv`), ``summary.md`` and ``subjects.csv`` (per-subject
    quality control, when subjects were assessed) into `out`.

    Parameters
    ----------
    result : EvaluationResult
    out : path
        Created if needed; files of other names in it are left alone, and one of these
        names that the toolkit did not write there is refused (InputError, nothing
        written).
    figures : bool
        Render and write the PNG figures (:func:`~.evaluation_figures.figure_pngs`) and
        ``report.html`` (:func:`~.evaluation_page.report_html`, embedding the same bytes);
        False: the text files only.

    Returns
    -------
    list of Path
        The files written.
    """
    pngs = figure_pngs(result) if figures else {}
    # build everything before writing any file
    texts = {
        "results.json": results_json(result),
        "results.csv": results_csv(result),
        "metrics.csv": metrics_csv(result),
        "summary.md": summary_table(result),
    }
    if any(s.subjects for s in result.scores.values()):
        texts["subjects.csv"] = subjects_csv(result)
    page = {"report.html": report_html(result, figures=pngs)} if figures else {}
    out = claim_entries(out, [*pngs, *page, *texts], command="evaluate")
    written = []
    for fname, data in pngs.items():
        with atomic_path(out / fname) as tmp:
            tmp.write_bytes(data)
        written.append(out / fname)
    for fname, text in {**page, **texts}.items():
        write_text(out / fname, text)
        written.append(out / fname)
    return written
