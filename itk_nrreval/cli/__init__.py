"""The ``nrreval`` command line.

Each sub-command lives in its own module of this package and provides
``add_parser(subparsers)``, which registers its arguments and sets ``func`` to a function
taking the parsed arguments and returning an exit code. Bad input (:class:`InputError`)
becomes one line on stderr and exit code 2, a failed registration engine
(:class:`EngineError`) one line and exit code 1: never a traceback.
"""

from __future__ import annotations

import argparse
import sys

from .._errors import EngineError, InputError
from . import demo, diagnose, evaluate, overlap, register, specificity, synth, validate

__all__ = ["main"]

# One entry per sub-command module, in the order `nrreval --help` lists them.
COMMANDS = [demo, evaluate, specificity, overlap, synth, register, validate, diagnose]


def build_parser() -> argparse.ArgumentParser:
    from .._version import __version__

    parser = argparse.ArgumentParser(
        prog="nrreval",
        description="Evaluate non-rigid registrations of a group of images without ground truth.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"nrreval {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except EngineError as exc:
        print(f"nrreval {args.command}: engine error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"nrreval {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
