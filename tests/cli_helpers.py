"""Run the `dtoc` CLI in-process for tests: exit code, stdout and stderr."""

from dtoc.cli.main import run


def run_cli(capsys, *argv):
    """Call the console entry point with ``argv``; return (exit code, stdout, stderr)."""
    code = 0
    try:
        run(list(map(str, argv)))
    except SystemExit as e:
        code = e.code or 0
    out = capsys.readouterr()
    return code, out.out, out.err
