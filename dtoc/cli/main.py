"""`dtoc` command-line entry point: a thin typer layer over the library.

Each stage registers its own commands from its own module (``dtoc.cli.<stage>_cmds.register``),
so the layers stay separate.  Every :class:`dtoc.errors.DtocError`, OS error (read-only folder, full
disk), and any unexpected exception becomes a single ``dtoc: error: ...`` line on stderr and a non-zero
exit (docs/cli.md: 1 check failed, 2 bad input or environment, 3 internal error, 130/143 interrupted);
set ``DTOC_DEBUG=1`` to see the traceback of an unexpected error.
"""

from __future__ import annotations

import os
import sys

import typer

from dtoc.version import __version__

app = typer.Typer(
    name="dtoc",
    help="MRI sequence compiler: pre-compensates Pulseq gradients through a differentiable digital twin.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version_cb(value: bool):
    if value:
        typer.echo(f"dtoc {__version__}")
        raise typer.Exit(0)


@app.callback()
def _main(
    version: bool = typer.Option(
        False, "--version", callback=_version_cb, is_eager=True, help="Print the version and exit."
    ),
):
    """dtoc: build, check, simulate and pre-compensate MRI sequences for real gradient hardware."""


def _register_all():
    from dtoc.cli import batch_cmds, hardware_cmds, identify_cmds, optimize_cmds, seq_cmds, sim_cmds

    for mod in (seq_cmds, hardware_cmds, sim_cmds, optimize_cmds, identify_cmds, batch_cmds):
        mod.register(app)


_register_all()


def error_exit(message: str, code: int = 2) -> None:
    """Print one error line to stderr and exit with ``code``."""
    sys.stderr.write(f"dtoc: error: {' '.join(str(message).split())}\n")
    sys.stderr.flush()
    raise SystemExit(code)


def _interrupt_cause(e: BaseException) -> KeyboardInterrupt | None:
    """The KeyboardInterrupt behind an exit, if any (followed through __cause__/__context__)."""
    cur: BaseException | None = e
    for _ in range(10):
        if cur is None:
            break
        if isinstance(cur, KeyboardInterrupt):
            return cur
        cur = cur.__cause__ or cur.__context__
    return None


def _interrupted(e: KeyboardInterrupt) -> None:
    """One line and exit 130 (SIGINT) / 143 (SIGTERM)."""
    from dtoc.util import interrupt

    signum = getattr(e, "signum", None)
    done = getattr(e, "outputs_complete", False)
    what = "the outputs were complete and are written" if done else "no output written"
    sys.stderr.write(f"dtoc: interrupted by {interrupt.signal_name(signum)}: {what}\n")
    sys.stderr.flush()
    raise SystemExit(interrupt.exit_code(signum)) from None


def _one_line_usage_errors() -> None:
    """A usage error (unknown option, missing argument, a value the parser refuses) is one ``dtoc: error:`` line
    (exit 2, as click's) instead of typer's boxed panel; a bare ``dtoc`` or group still shows its help."""
    from typer import _click as click
    from typer import rich_utils

    boxed = rich_utils.rich_format_error
    if getattr(boxed, "_dtoc_one_line", False):
        return

    def one_line(e) -> None:
        if isinstance(e, click.exceptions.NoArgsIsHelpError):
            boxed(e)
            return
        ctx = getattr(e, "ctx", None)
        cmd = ctx.command_path if ctx is not None else "dtoc"
        msg = " ".join(e.format_message().split())
        sys.stderr.write(f"dtoc: error: {cmd}: {msg} (see '{cmd} --help')\n")
        sys.stderr.flush()

    one_line._dtoc_one_line = True  # type: ignore[attr-defined]
    rich_utils.rich_format_error = one_line


def run(argv: list[str] | None = None) -> None:
    """Console-script entry point."""
    from dtoc.errors import DtocError, describe
    from dtoc.util import interrupt
    from dtoc.util.allocator import keep_freed_memory

    interrupt.install()
    keep_freed_memory()
    import warnings

    # numpy's floating-point RuntimeWarnings are not for the user: a bad value is refused with one line
    warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"numpy(\.|$)")
    _one_line_usage_errors()
    try:
        app(args=argv, standalone_mode=True)
    except SystemExit as e:
        ki = _interrupt_cause(e)  # typer turns an interrupt into exit 130 without a word
        if ki is None:
            raise
        _interrupted(ki)
    except KeyboardInterrupt as e:
        _interrupted(e)
    except Exception as e:  # noqa: BLE001 - last line of defence: one line, never a traceback
        if os.environ.get("DTOC_DEBUG") and not isinstance(e, (DtocError, MemoryError, RecursionError, OSError)):
            raise
        error_exit(*describe(e))


if __name__ == "__main__":
    run()
