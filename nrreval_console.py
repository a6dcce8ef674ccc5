"""The ``nrreval`` program's entry point.

It lives outside the package so that Ctrl-C while the package imports (SimpleITK, ITK, numba:
about two seconds) ends as an interrupt at any other moment does: one line on stderr and
exit code 130, never a traceback.
"""

from __future__ import annotations

import os
import signal
import sys

INTERRUPTED = 130
"""The exit code after Ctrl-C (SIGINT): 128 + 2, as shells report it."""


def caused_by_interrupt(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt is anywhere in `exc`'s chain of causes and contexts.

    Ctrl-C that lands inside compiled code (a numba kernel, ITK, an extension module being
    imported) surfaces as the error that code raises on the way out -- numba's SystemError
    "returned a result with an exception set" -- with the KeyboardInterrupt as its context.
    """
    seen: set[int] = set()
    todo: list[BaseException | None] = [exc]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            return True
        todo += [e.__cause__, e.__context__]
    return False


def _interrupt(signum, frame) -> None:
    """Ctrl-C: a KeyboardInterrupt, unless the command's result is already in place.

    The command line (:func:`itk_nrreval.cli.main`) holds the same rule while its command
    runs, then restores this handler; this one covers the moments before and after it.
    Where the interrupted code is a callback whose exceptions Python ignores, the interrupt
    is asked for again shortly instead (:func:`_swallowed_in`).
    """
    output = sys.modules.get("itk_nrreval._output")
    if output is not None and output.swaps_done() > 0:
        return
    if _swallowed_in(frame):
        _ask_again()
        return
    raise KeyboardInterrupt


def _swallowed_in(frame) -> bool:
    """Whether an exception raised in `frame` would be ignored: Python prints "Exception
    ignored in ...", a traceback, and carries on. So it is in the import system's weakref
    callback (``_get_module_lock.<locals>.cb``, run while the package imports) and in any
    ``__del__``: a Ctrl-C raised there was lost, with a traceback on stderr."""
    if frame is None:
        return False
    code = frame.f_code
    return code.co_name == "__del__" or (code.co_name == "cb" and "importlib" in code.co_filename)


def _ask_again(delay_s: float = 0.05) -> None:
    """Send this process SIGINT again in `delay_s` seconds, from a daemon thread (signals are
    handled in the main thread, which by then has left the callback)."""
    import threading

    timer = threading.Timer(delay_s, os.kill, (os.getpid(), signal.SIGINT))
    timer.daemon = True
    timer.start()


def main() -> None:
    """Run ``nrreval`` and exit with its code.

    After Ctrl-C the process ends at once (``os._exit``), once the command has cleaned up
    and printed its line: worker threads still inside ITK or numba would otherwise be stopped
    mid-call by the interpreter's shutdown, which can abort the process ("FATAL: exception
    not rethrown") or print their tracebacks. Everything written so far went through
    temporary names, and a stale temporary is removed by the next run.
    """
    signal.signal(signal.SIGINT, _interrupt)
    try:
        from itk_nrreval.cli import main as command

        code = command()
    except BaseException as exc:
        if isinstance(exc, SystemExit) or not caused_by_interrupt(exc):
            raise
        print("nrreval: interrupted", file=sys.stderr)
        code = INTERRUPTED
    if code == INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    # The command is over and its result complete: a Ctrl-C now would land in the
    # interpreter's shutdown, after its own handler is gone, and kill the process with no
    # word (exit -2) instead of the exit code the result deserves.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    main()
