"""The ``nrreval`` command line.

Each sub-command lives in its own module of this package and provides
``add_parser(subparsers)``, which registers its arguments and sets ``func`` to a function
taking the parsed arguments and returning an exit code. Bad input (:class:`InputError`)
becomes one line on stderr and exit code 2, a failed registration engine
(:class:`EngineError`) one line and exit code 1, Ctrl-C one line and exit code 130: never a
traceback.
"""

from __future__ import annotations

import sys
import warnings

from nrreval_console import INTERRUPTED, caused_by_interrupt

from .. import _output
from .._errors import EngineError, InputError
from . import (
    demo,
    diagnose,
    evaluate,
    manifest,
    overlap,
    register,
    specificity,
    sweep,
    synth,
    validate,
)
from ._options import OneLineParser

__all__ = ["main"]

# One entry per sub-command module, in the order `nrreval --help` lists them.
COMMANDS = [
    demo,
    evaluate,
    manifest,
    specificity,
    overlap,
    synth,
    register,
    sweep,
    validate,
    diagnose,
]


def build_parser() -> OneLineParser:
    from .._version import __version__

    parser = OneLineParser(
        prog="nrreval",
        description="Evaluate non-rigid registrations of a group of images without ground truth.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    sub.required = True
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def _interrupts_dropped_once_complete():
    """Ctrl-C ends the command (exit code 130: the previous result is kept) until the
    command's result has been swapped into place (:func:`itk_nrreval._output.staged_folder`);
    after that it is dropped, and the little that is left (the summary printed) runs out.

    Without this, an interrupt between the swap and the end of the command ended it with 130
    over a replaced result.
    """
    swaps_before = _output.swaps_done()

    def interrupt(signum, frame):
        if _output.swaps_done() > swaps_before:
            return
        raise KeyboardInterrupt

    return _output.sigint_handled_by(interrupt)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error (one line on stderr)
        return int(exc.code or 0)

    def one_line(message, category, filename, lineno, file=None, line=None):
        # a warning is for the user, not the developer: no source file, no source line
        print(f"nrreval {args.command}: warning: {message}", file=sys.stderr)

    try:
        with warnings.catch_warnings(), _interrupts_dropped_once_complete():
            warnings.showwarning = one_line  # catch_warnings restores it on the way out
            return int(args.func(args) or 0)
    except InputError as exc:
        print(f"nrreval {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except EngineError as exc:
        print(f"nrreval {args.command}: engine error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"nrreval {args.command}: interrupted", file=sys.stderr)
        return INTERRUPTED
    except Exception as exc:
        # Ctrl-C that lands inside compiled code (a numba kernel, ITK) surfaces as the error
        # that code raises on the way out (numba's SystemError "returned a result with an
        # exception set"), with the KeyboardInterrupt as its cause or context.
        if not caused_by_interrupt(exc):
            raise
        print(f"nrreval {args.command}: interrupted", file=sys.stderr)
        return INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
