"""SIGINT and SIGTERM as one exception that remembers its signal.

The command line installs :func:`install` once: both signals then raise :class:`Interrupted` (a
``KeyboardInterrupt``, so every ``except KeyboardInterrupt`` that keeps a best-so-far handles SIGTERM
too), and :func:`exit_code` gives 130 for SIGINT and 143 for SIGTERM (128 + signal number).

:func:`fault_point` is the test hook: with ``DTOC_FAULT_SIGNAL=stage:SIGNAME`` in the environment the
process sends itself that signal when it reaches ``stage`` (docs/cli.md lists the stages), so the tests
interrupt a real process at a known point instead of guessing a time.
"""

from __future__ import annotations

import os
import signal

_last_signal: int | None = None


class Interrupted(KeyboardInterrupt):
    """Raised by the installed handler; ``signum`` is the signal received."""

    def __init__(self, signum: int, outputs_complete: bool = False) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        #: True when raised after a :class:`deferred` block finished writing its outputs
        self.outputs_complete = outputs_complete


def _handler(signum, frame) -> None:
    global _last_signal
    _last_signal = signum
    raise Interrupted(signum)


def install() -> None:
    """Route SIGINT and SIGTERM to :class:`Interrupted` (main thread only; a no-op elsewhere)."""
    try:
        signal.signal(signal.SIGINT, _handler)
        signal.signal(signal.SIGTERM, _handler)
    except ValueError:  # not the main thread
        pass


def last_signal() -> int | None:
    """The last signal received since :func:`install` (None: none)."""
    return _last_signal


def signal_name(signum: int | None = None) -> str:
    s = signum if signum is not None else (_last_signal or signal.SIGINT)
    return signal.Signals(s).name


def exit_code(signum: int | None = None) -> int:
    """128 + the signal number: 130 for SIGINT (also a plain KeyboardInterrupt), 143 for SIGTERM."""
    return 128 + int(signum if signum is not None else (_last_signal or signal.SIGINT))


#: Stages a test can interrupt with ``DTOC_FAULT_SIGNAL=stage:SIGNAME``.
FAULT_STAGES = ("setup", "warm_start", "full_loss", "verify", "export", "batch_job")


def fault_point(stage: str) -> None:
    """Send the signal named in ``DTOC_FAULT_SIGNAL`` to this process when it names ``stage`` (test hook)."""
    spec = os.environ.get("DTOC_FAULT_SIGNAL")
    if not spec or ":" not in spec:
        return
    where, name = spec.split(":", 1)
    if where != stage:
        return
    os.environ.pop("DTOC_FAULT_SIGNAL", None)  # once
    os.kill(os.getpid(), getattr(signal, name))


class signals_ignored:
    """Context manager: SIGINT/SIGTERM ignored inside the block (for a clean-up that a second Ctrl-C must not
    cut short; unlike :class:`deferred`, nothing is raised afterwards).  Main thread only; elsewhere a no-op."""

    def __init__(self) -> None:
        self._old: dict[int, object] = {}

    def __enter__(self) -> signals_ignored:
        try:
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.signal(s, signal.SIG_IGN)
        except ValueError:  # not the main thread
            self._old.clear()
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)  # type: ignore[arg-type]


class deferred:
    """Context manager: SIGINT/SIGTERM received inside the block are held until its end, then raised as
    :class:`Interrupted` (so that a block that writes outputs finishes them).  Main thread only; elsewhere
    the block runs unprotected.

    ``held=False``: a signal raises :class:`Interrupted` at once, as outside the block, until :meth:`hold` is
    called; from then on it waits for the block's end (a block that prepares its outputs for minutes, then
    commits them: only the commit waits)."""

    def __init__(self, held: bool = True) -> None:
        self._got: int | None = None
        self._old: dict[int, object] = {}
        self._held = held

    def hold(self) -> None:
        """From now on a signal waits until the end of the block."""
        self._held = True

    def _record(self, signum, frame) -> None:
        global _last_signal
        _last_signal = signum
        if not self._held:
            raise Interrupted(signum)
        self._got = self._got or signum

    def __enter__(self) -> deferred:
        try:
            for s in (signal.SIGINT, signal.SIGTERM):
                self._old[s] = signal.signal(s, self._record)
        except ValueError:  # not the main thread
            self._old.clear()
        return self

    def __exit__(self, *exc) -> None:
        for s, h in self._old.items():
            signal.signal(s, h)  # type: ignore[arg-type]
        if self._got is not None and exc[0] is None:
            raise Interrupted(self._got, outputs_complete=True)
