"""The ``rflscm`` command line: a thin Typer app over the library.

Each command lives in its own module and registers itself on :data:`app`.
User mistakes surface as :class:`rflscm.errors.RflscmError`; :func:`main`
catches them once, prints one line to stderr and exits with code 2.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

# OpenMP threads that spin while idle make torch's many small CPU ops several times slower as soon as
# another process competes for the cores (experiments/omp_contention.py; 2 cores, 3 busy processes:
# 13.6 s vs 2.6 s) and cost nothing on an idle machine.  Read when torch loads, hence before imports.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import typer

from rflscm import LOADED_AT, __version__
from rflscm.cli.common import Interrupted, ThreadsOption, mark_command_start, set_threads
from rflscm.errors import RflscmError
from rflscm.runtime import keep_freed_memory

app = typer.Typer(
    name="rflscm",
    help="Learn localized statistical channel models (RF-LSCM) from multi-beam RSRP and predict coverage "
    "after antenna changes.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _plain_flags() -> None:
    """Typer ≥ 0.2x writes a ``<bool>`` type beside every flag (``--help <bool>``, ``--kpi <bool>``) though a flag
    takes no value; show no type for flags, as click does."""
    from typer.core import TyperOption

    shown = TyperOption.display_type_rich

    def display_type_rich(self: TyperOption, ctx: object) -> str | None:
        if getattr(self, "is_flag", False) or getattr(self, "is_bool_flag", False):
            return None
        return shown(self, ctx)  # type: ignore[arg-type]

    TyperOption.display_type_rich = display_type_rich  # type: ignore[method-assign]


_plain_flags()


def _version(value: bool) -> None:
    if value:
        typer.echo(f"rflscm {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
    threads: int | None = ThreadsOption,
) -> None:
    """rflscm: radiance-field channel models from multi-beam RSRP."""
    set_threads(threads)  # before any command runs
    keep_freed_memory()  # renders re-use their large buffers instead of faulting fresh pages in (rflscm.runtime)


def _register_commands() -> None:
    # Imported for their side effect of adding commands to `app`.
    from rflscm.cli import bench, check, demo, evaluate, import_, map, optimize, predict, simulate, train  # noqa: F401


def _raise_interrupted(signum: int, frame: object) -> None:
    raise Interrupted(signum)


def _report_interrupted(exc: Interrupted) -> None:
    """One line on stderr (what was saved, how to resume), then exit 128 + the signal number (130, 143)."""
    name = signal.Signals(exc.signum).name
    saved = exc.saved or (
        "no output was left half-written (every file is written to a temporary name and renamed when complete)"
    )
    print(f"Interrupted: {name} stopped the run; {saved}", file=sys.stderr)
    sys.exit(128 + exc.signum)


_LOADED = [LOADED_AT]
"""The package's import time, for the first command run in this process (a later one counts from its own start)."""


def main() -> None:
    """Console-script entry point."""
    # the first command's budget counts from the package's import (torch's among the imports), as a stopwatch would
    mark_command_start(_LOADED.pop() if _LOADED else None)
    _register_commands()
    previous: dict[signal.Signals, signal._HANDLER] = {}
    for signum in (signal.SIGINT, signal.SIGTERM):  # both are failures, never a silent exit 0
        with contextlib.suppress(ValueError):  # not the main thread (an embedding program): keep its handlers
            previous[signum] = signal.signal(signum, _raise_interrupted)
    try:
        code = app(standalone_mode=False)
    except Interrupted as exc:
        _report_interrupted(exc)
    except KeyboardInterrupt:  # a SIGINT before our handler was in place
        _report_interrupted(Interrupted(signal.SIGINT))
    except RflscmError as exc:
        message = " ".join(str(exc).split())  # one line, whatever text from a file the message quotes
        print(f"{type(exc).__name__}: {message}", file=sys.stderr)
        sys.exit(2)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        print("Aborted.", file=sys.stderr)
        sys.exit(1)
    except Exception as exc:  # click usage errors carry their own exit code
        if isinstance(exc, _click_exceptions()):  # one line, like our own errors (a wrong choice, a missing argument)
            message = " ".join(exc.format_message().replace("Value error, ", "").split())  # type: ignore[attr-defined]
            ctx = getattr(exc, "ctx", None)
            hint = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
            print(f"Error: {message}{hint}", file=sys.stderr)
            sys.exit(exc.exit_code)  # type: ignore[attr-defined]
        raise
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    if isinstance(code, int) and code:  # typer returns the code of an Exit raised inside a command
        sys.exit(code)


def _click_exceptions() -> tuple[type[Exception], ...]:
    """Click's usage-error base class: typer ≥ 0.2x raises those of the click copy it vendors
    (``typer._click``), not the ``click`` package's, so both are recognised."""
    classes: list[type[Exception]] = []
    try:
        from typer._click.exceptions import ClickException as Vendored

        classes.append(Vendored)
    except ImportError:  # a typer that uses the click package
        pass
    try:
        import click

        classes.append(click.ClickException)
    except ImportError:
        pass
    return tuple(classes)
