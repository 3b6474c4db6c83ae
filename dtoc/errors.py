"""One exception type for every user-facing failure.

Library code raises :class:`DtocError` (or a subclass) with a one-line message that names the
problem (the file, the key, the expected shape or unit).  The CLI prints ``dtoc: error: <message>``
to stderr and exits with :attr:`DtocError.exit_code`; it never shows a traceback for these.
"""


class DtocError(Exception):
    """A user-facing error: bad input, impossible request, failed validation."""

    exit_code: int = 2

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))  # always one line


class InputError(DtocError):
    """A file or argument given by the user is missing, malformed or out of range."""


class LimitError(DtocError):
    """A hardware limit is violated or cannot be met."""


class ValidationFailed(DtocError):
    """`dtoc check` / `dtoc diff` style failure (exit 1)."""

    exit_code = 1


def describe(e: BaseException) -> tuple[str, int]:
    """(one-line message, exit code) of an error that ends a command (docs/cli.md: 2 bad input or environment,
    3 internal error): what ``dtoc`` prints after ``dtoc: error:``, and what a ``dtoc batch`` job reports."""
    if isinstance(e, DtocError):
        return str(e), e.exit_code
    if isinstance(e, MemoryError):
        return "out of memory: the input is larger than this machine can hold (see docs/cli.md, input bounds)", 2
    if isinstance(e, RecursionError):
        return "input nested too deeply to parse", 2
    if isinstance(e, OSError):
        where = f"{e.filename}: " if e.filename else ""
        return " ".join(f"{where}{e.strerror or e}".split()), 2
    return " ".join(f"unexpected {type(e).__name__}: {e}".split()), 3
