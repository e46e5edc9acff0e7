"""The ``eyetohand`` command: parse, call the library, print, set the exit code.

Exit codes: 0 ok; 2 bad input (one ``error:`` line on stderr); 1 internal failure; 130 Ctrl-C (one
``error: interrupted`` line, in every command: tests/test_first_day_trips.py).
The commands live in this package only, one module per group, each with ``register(subparsers)``
(listed in ``COMMAND_MODULES``, in the order of ``eyetohand --help``). Library modules print nothing
and never import this package.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import signal
import sys

from eyetohand._version import __version__
from eyetohand.cli.common import CliError
from eyetohand.core import InputError

# Modules that add subcommands; each has register(subparsers).
COMMAND_MODULES = (
    "eyetohand.cli.calibrate",
    "eyetohand.cli.demo",
    "eyetohand.cli.report",
    "eyetohand.cli.serve",
    "eyetohand.cli.sim",
    "eyetohand.cli.images",
    "eyetohand.cli.plate",
    "eyetohand.cli.grab",
    "eyetohand.cli.conveyor",
    "eyetohand.cli.export",
    "eyetohand.cli.verify",
    "eyetohand.cli.diff",
    "eyetohand.cli.store",
    "eyetohand.cli.sign",
)


#: each command → the module that registers it (tests/test_cli.py checks this table against the modules):
#: ``eyetohand apply …`` imports and registers only its own module, not every command's library.
_COMMANDS = {
    "calibrate": "eyetohand.cli.calibrate",
    "evaluate": "eyetohand.cli.calibrate",
    "apply": "eyetohand.cli.calibrate",
    "compare": "eyetohand.cli.calibrate",
    "demo": "eyetohand.cli.demo",
    "report": "eyetohand.cli.report",
    "serve": "eyetohand.cli.serve",
    "simulate": "eyetohand.cli.sim",
    "plan": "eyetohand.cli.sim",
    "detect": "eyetohand.cli.images",
    "calibrate-images": "eyetohand.cli.images",
    "calibrate-plate": "eyetohand.cli.plate",
    "grab": "eyetohand.cli.grab",
    "conveyor": "eyetohand.cli.conveyor",
    "export": "eyetohand.cli.export",
    "verify": "eyetohand.cli.verify",
    "diff": "eyetohand.cli.diff",
    "crossval": "eyetohand.cli.diff",
    "audit": "eyetohand.cli.store",
    "store": "eyetohand.cli.store",
    "sign": "eyetohand.cli.sign",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # argparse's own errors: one line, exit 2
        raise CliError(f"{self.prog}: {message}")


def build_parser() -> argparse.ArgumentParser:
    return _build(COMMAND_MODULES)


def _build(modules: tuple[str, ...]) -> argparse.ArgumentParser:
    parser = _Parser(prog="eyetohand", description="Eye-to-hand camera-to-robot calibration.")
    parser.add_argument("--version", action="version", version=f"eyetohand {__version__}")
    sub = parser.add_subparsers(dest="command", parser_class=_Parser, metavar="COMMAND")
    for name in modules:
        importlib.import_module(name).register(sub)
    return parser


@functools.cache
def _parser(module: str | None = None) -> argparse.ArgumentParser:
    """The parser :func:`main` uses, built once per process (~6 ms): parsing does not change it, and
    a program or test that calls ``main`` many times need not rebuild 17 subcommands each time.
    With ``module``, only that command module's commands: what ``eyetohand apply …`` needs."""
    return build_parser() if module is None else _build((module,))


def _module_of(argv) -> str | None:
    """The command module of the command ``argv`` starts with; None (every command) for anything else:
    ``--help``, ``--version``, no command, an unknown one."""
    args = sys.argv[1:] if argv is None else list(argv)
    return _COMMANDS.get(args[0]) if args else None


class _Interrupt:
    """Ctrl-C, seen by the command whatever a library makes of it: the signal handler raises
    KeyboardInterrupt as Python's does, and remembers the signal, so an interrupt that a library turns
    into another exception (NumPy, a thread pool) still ends as one ``error: interrupted`` line, 130."""

    seen = False

    @classmethod
    def handler(cls, signum, frame):
        cls.seen = True
        raise KeyboardInterrupt

    @classmethod
    def install(cls) -> None:
        cls.seen = False
        try:  # Python's own handler only: an ignored SIGINT (nohup, a service) stays ignored
            if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
                signal.signal(signal.SIGINT, cls.handler)
        except ValueError:  # not the main thread (main called from a thread): Python's rule stands
            pass


def _interrupted() -> int:
    """Ctrl-C reported: one line, 130. From here on the command is ending, and SIGINT is ignored: a
    second Ctrl-C while the process winds down (threads joined, files closed) would otherwise end it
    with a traceback after the line was printed.

    CPython remembers a KeyboardInterrupt that ended code run from a string (``exec``/``eval``
    of text: dataclasses and namedtuples build their methods so) in a flag that outlives the
    ``except`` that caught it; ``Py_RunMain`` reads that flag at exit and kills the process with
    SIGINT (exit -2, not 130) -- Ctrl-C during an import that defines dataclasses did that to
    ``serve``. Running an empty string resets the flag (``run_eval_code_obj`` in
    Python/pythonrun.c): the interrupt was handled here."""
    print("error: interrupted", file=sys.stderr)
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:  # not the main thread: nothing was installed here either
        pass
    exec("")  # noqa: S102 -- resets CPython's "unhandled KeyboardInterrupt" flag, see above
    return 130


def main(argv=None) -> int:
    _Interrupt.install()
    try:
        args = _parser(_module_of(argv)).parse_args(argv)
        if not getattr(args, "func", None):
            _parser().print_help()
            return 2
        return int(args.func(args) or 0)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted()
    except BrokenPipeError:
        return 0
    except Exception as exc:  # internal failure: one line unless debugging
        if _Interrupt.seen:  # Ctrl-C, turned into another exception on its way out
            return _interrupted()
        if os.environ.get("EYETOHAND_DEBUG"):
            raise
        print(
            f"internal error: {type(exc).__name__}: {exc} (set EYETOHAND_DEBUG=1 for details)",
            file=sys.stderr,
        )
        return 1


__all__ = ["CliError", "COMMAND_MODULES", "build_parser", "main"]
