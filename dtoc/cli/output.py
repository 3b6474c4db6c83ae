"""The one output convention of every dtoc command (docs/cli.md).

- The human table goes to stdout; progress, warnings, notes and "wrote X" lines go to stderr.
- ``--json PATH`` writes the machine report to PATH (atomically, with the command's other outputs);
  ``--json -`` writes it to stdout, and the table then moves to stderr so that stdout parses as JSON.
- Exit codes: 0 ok, 1 check failed (``check``, ``diff``), 2 bad input, 130 interrupted (143 for SIGTERM).

Report keys carry their unit in the name (``_percent``, ``_dk``, ``_rad_per_m``, ``_mT_per_m``, ``_s``,
``n_`` for counts); :func:`dtoc.sim.metrics.report_figures` maps the library's internal figure names
(fractions) onto them.
"""

from __future__ import annotations

import sys

import typer


def json_option(what: str):
    """The ``--json`` option of every command: a path, or '-' for stdout."""
    return typer.Option(
        None, "--json", help=f"write {what} as JSON to this path ('-' = stdout; the table then goes to stderr)"
    )


class Output:
    """Where one command's table and report go, following the convention above."""

    def __init__(self, json_target: str | None) -> None:
        self.json_target = None if json_target is None else str(json_target)

    @property
    def json_to_stdout(self) -> bool:
        return self.json_target == "-"

    def console(self):
        """A rich console on stdout (stderr when the JSON report owns stdout); wide when not a terminal."""
        from rich.console import Console

        f = sys.stderr if self.json_to_stdout else sys.stdout
        con = Console(file=f, highlight=False)
        return con if con.is_terminal else Console(file=f, width=160, highlight=False)

    def write_json(self, text: str, force: bool) -> None:
        """Write the report: to stdout for '-', else atomically to the path (joins :func:`outputs_together`)."""
        if self.json_target is None:
            return
        if self.json_to_stdout:
            sys.stdout.write(text)
            sys.stdout.flush()
            return
        from dtoc.util.atomic import atomic_write_text

        atomic_write_text(self.json_target, text, force=force)


def sequence_notes(ir) -> None:
    """The reader's notes on a sequence (e.g. how an undefined RF use was taken), one stderr line each."""
    for n in (getattr(ir, "meta", None) or {}).get("notes", []):
        note(f"note: {n}")


def note(line: str) -> None:
    """One line on stderr (wrote ..., note: ..., warning: ...)."""
    sys.stderr.write(line.rstrip("\n") + "\n")
    sys.stderr.flush()
