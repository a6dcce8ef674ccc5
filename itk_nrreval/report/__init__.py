"""Everything a person looks at: figures, pages, tables and the text files of every result.

The domain modules compute; to write they call the functions here (``result.write(folder)``
comes here), and only the modules of this package import matplotlib (inside their functions,
without pyplot: the process's backend is left alone).

* :mod:`.evaluation` (with :mod:`.evaluation_text`, :mod:`.evaluation_figures` and
  :mod:`.evaluation_page`): ``evaluate``'s figures, ``report.html``, ``summary.md`` and CSV;
* :mod:`._plot`, :mod:`._html`, :mod:`._format`: the plot helpers, HTML pieces and number
  formats every page shares.
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
