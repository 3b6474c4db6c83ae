"""`dtoc` command-line entry point: a thin typer layer over the library.

Each stage registers its own commands from its own module (``dtoc.cli.<stage>_cmds.register``),
so the layers stay separate.  Every :class:`dtoc.errors.DtocError` (and any unexpected exception)
becomes a single ``dtoc: error: ...`` line on stderr and a non-zero exit; set ``DTOC_DEBUG=1`` to see
the traceback of an unexpected error.
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
    from dtoc.cli import hardware_cmds, identify_cmds, optimize_cmds, seq_cmds, sim_cmds

    for mod in (seq_cmds, hardware_cmds, sim_cmds, optimize_cmds, identify_cmds):
        mod.register(app)


_register_all()


def error_exit(message: str, code: int = 2) -> None:
    """Print one error line to stderr and exit with ``code``."""
    sys.stderr.write(f"dtoc: error: {' '.join(str(message).split())}\n")
    sys.stderr.flush()
    raise SystemExit(code)


def run(argv: list[str] | None = None) -> None:
    """Console-script entry point."""
    from dtoc.errors import DtocError

    try:
        app(args=argv, standalone_mode=True)
    except SystemExit:
        raise
    except DtocError as e:
        error_exit(str(e), e.exit_code)
    except KeyboardInterrupt:
        error_exit("interrupted", 130)
    except Exception as e:  # noqa: BLE001 - last line of defence: one line, never a traceback
        if os.environ.get("DTOC_DEBUG"):
            raise
        error_exit(f"unexpected {type(e).__name__}: {e}", 3)


if __name__ == "__main__":
    run()
