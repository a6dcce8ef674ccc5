"""Everything a person looks at: the figures, pages, tables and text files of every result.

The domain modules compute; to write they call this package (``result.write(folder)`` comes
here), and only its modules import matplotlib (inside their functions, without pyplot: the
process's backend is left alone). Its modules take the results without importing their
classes, since the domain modules import them to write.

* :mod:`.evaluation` (:func:`write_evaluation`), with :mod:`.evaluation_text` (summary.md,
  results.csv/json, subjects.csv), :mod:`.evaluation_figures` and :mod:`.evaluation_page`
  (report.html): ``evaluate``;
* :mod:`.validation`: ``validate``'s Fig. 2, specificity against d and report.html;
* :mod:`.sweep`: ``sweep``'s figure and report.html;
* :mod:`.diagnostics`: ``diagnose``'s Table 1 and cell-population bars;
* :mod:`._plot`, :mod:`._html`, :mod:`._format`: the plot helpers, HTML pieces and number
  formats they share.
"""

from ._format import format_number, format_percent
from .evaluation import write_evaluation
from .evaluation_text import FLAGGED_SUBJECTS_SHOWN, format_rank, summary_table

__all__ = [
    "FLAGGED_SUBJECTS_SHOWN",
    "format_number",
    "format_percent",
    "format_rank",
    "summary_table",
    "write_evaluation",
]
