"""Stopping a run on request: SIGTERM and SIGUSR1 end training at the next update with a checkpoint.

SLURM sends SIGTERM before it kills a job at its time limit or on preemption (and SIGUSR1, or any
signal, when asked with ``--signal=B:USR1@<seconds>``); ``kill <pid>`` sends SIGTERM too. While a
:class:`~drone_torchrl.training.trainer.Trainer` trains, these signals only raise a flag: the loop
finishes the update in flight, books its episodes, writes every active run's checkpoint and raises
:class:`TrainingStopped`, and the command exits with ``128 + the signal's number`` (143 for SIGTERM,
138 for SIGUSR1), the shell's convention for a command ended by a signal. Resuming then trains no
episode twice and loses none. SIGINT (Ctrl-C) stays Python's ``KeyboardInterrupt``: an immediate
stop that keeps the last periodic checkpoint.

Work with nothing to checkpoint (``drone-export``) stops at once instead (:func:`interrupt_on_signals`):
the signal raises :class:`Interrupted`, so the temporary files of a write in flight are removed
(:func:`drone_torchrl.io.storage.writing`) rather than left behind by a process the OS ended.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

#: The signals that stop training cleanly, with a checkpoint (see the module's description).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)


class Interrupted(BaseException):
    """A stop signal received inside :func:`interrupt_on_signals`, raised where the program was.

    So ``finally`` blocks and :func:`~drone_torchrl.io.storage.writing` clean up on the way out.
    A ``BaseException``, like ``KeyboardInterrupt``: it is not a failure of the job, so the handlers
    that record failed jobs (``except Exception``) let it pass to the command, which exits with
    :attr:`exit_code`.

    Args:
        signum: the signal received.
    """

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")

    @property
    def exit_code(self) -> int:
        """The command's exit status, ``128 +`` the signal's number."""
        return 128 + self.signum


class TrainingStopped(Interrupted):
    """Training ended early on a signal, every active run checkpointed.

    Args:
        signum: the signal that stopped training.
        run_dirs: the folders of the runs checkpointed.
    """

    def __init__(self, signum: int, run_dirs: list[Path]) -> None:
        super().__init__(signum)
        self.run_dirs = run_dirs


class StopRequest:
    """The signal received while training, if any."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __call__(self, signum: int, frame: object) -> None:
        """Record the signal (the handler of each stop signal)."""
        self.signum = signum


_active: list[StopRequest] = []  # the request of the outermost block running now (nested blocks share it)


@contextmanager
def _handling(handler: Callable[[int, object], None]) -> Iterator[None]:
    """``handler`` for :data:`STOP_SIGNALS` while the block runs; the handlers in place before after.

    Outside the main thread Python cannot install handlers: the signals keep their meaning.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, handler) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


@contextmanager
def stop_on_signals() -> Iterator[StopRequest]:
    """Catch :data:`STOP_SIGNALS` as a :class:`StopRequest` while the block runs.

    The handlers in place before are restored after. Blocks nest: an inner one shares the outer one's request,
    so a signal between two trainings of one command is not lost. Outside the main thread Python cannot
    install handlers: the request then never fires and the signals keep their previous meaning.
    """
    if _active:
        yield _active[0]
        return
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    _active.append(request)
    try:
        with _handling(request):
            yield request
    finally:
        _active.clear()


def _interrupt(signum: int, frame: object) -> None:
    raise Interrupted(signum)


def interrupt_on_signals() -> contextlib.AbstractContextManager[None]:
    """Make :data:`STOP_SIGNALS` raise :class:`Interrupted` while the block runs.

    The handlers in place before are restored after; outside the main thread the signals keep
    their meaning.
    """
    return _handling(_interrupt)
