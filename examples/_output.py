"""Where the examples write: the folder given with ``--out``, or a temporary one they remove.

Examples never write into the repository (nor into the current folder): run one with
``--out DIR`` to keep what it writes.
"""

from __future__ import annotations

import argparse
import contextlib
import tempfile
from collections.abc import Iterator
from pathlib import Path


def add_out_option(parser: argparse.ArgumentParser) -> None:
    """The ``--out DIR`` option every example takes."""
    parser.add_argument(
        "--out",
        metavar="DIR",
        help="keep what the example writes in DIR (default: a temporary folder, removed)",
    )


@contextlib.contextmanager
def output_folder(out: str | None, *, prefix: str) -> Iterator[Path]:
    """`out` (created if needed), or a temporary folder removed on leaving the block."""
    if out is not None:
        folder = Path(out)
        folder.mkdir(parents=True, exist_ok=True)
        yield folder
        print(f"kept in {folder}")
        return
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        yield Path(tmp)
