"""What the commands show their user: a reader that went away, and the lines each run keeps in its log.

A command's output piped into ``head`` (or a terminal closed under it) makes the next write to
stdout or stderr raise :class:`BrokenPipeError`. That is no reason to stop training, nor to record
a job as failed: :func:`guard_broken_pipes` wraps both streams once, at each command's start, so
that a broken pipe points the stream at :data:`os.devnull` (Python's documented idiom) and the
command goes on; every ``print``, logging handler and progress bar writes through the wrappers.
Only ``EPIPE`` is handled: a full disk or any other error is raised as before.

:data:`console` is the logger of the lines a run shows (notes, ``resume:`` lines, the final
summary, the next steps): INFO lines go to stdout, WARNING and above to stderr, as text alone
(:class:`Terminal`). Hydra's job logging (``hydra/job_logging=drone``, ``conf/hydra/job_logging/``)
adds the job's log file (``<folder>/train.log``) to it, so the log holds what the terminal showed,
without the progress bar. A line about one run names it (``extra={"run_dir": ...}``, see
:func:`about`); :class:`RunLogs` appends it to that run's ``train.log`` where Hydra's file is
another one: a run resumed in its own folder, the jobs of the fused launcher trained together, a
population run.
"""

from __future__ import annotations

import errno
import logging
import os
import sys
from pathlib import Path
from typing import Any, TextIO


class _AlwaysOn(logging.Logger):
    """A logger that a logging config's ``disable_existing_loggers`` cannot silence.

    Hydra's ``hydra/job_logging=disabled`` (drone-export's) disables every logger it finds, and
    :data:`console`'s lines are a command's output, not diagnostics: they are shown all the same.
    """

    @property  # type: ignore[override]
    def disabled(self) -> bool:
        """Never: the lines are the command's output."""
        return False

    @disabled.setter
    def disabled(self, value: bool) -> None:
        pass


#: The logger of the lines a command shows its user (see the module's docstring).
console = logging.getLogger("drone_torchrl.console")
console.__class__ = _AlwaysOn  # the logger made under this name (a logging config may have made it first)
#: A run folder's log file, Hydra's job log (``${hydra.job.name}.log`` of ``drone-train``).
RUN_LOG = "train.log"
#: How a log file's lines look, as in Hydra's default job logging.
LOG_FORMAT = "[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"


def about(run_dir: str | Path) -> dict[str, Any]:
    """The ``extra`` of a :data:`console` line about the run in ``run_dir`` (:class:`RunLogs` files it there)."""
    return {"extra": {"run_dir": run_dir}}


class Terminal(logging.Handler):
    """Writes a record's message alone, as ``print`` would: INFO to stdout, WARNING and above to stderr.

    The streams are looked up at each line (not kept from when the handler was made): a test's
    captured streams and :func:`guard_broken_pipes`' wrappers are the ones written to.
    """

    def emit(self, record: logging.LogRecord) -> None:
        """Write ``record``'s message and a newline to stdout or stderr."""
        try:
            stream = sys.stderr if record.levelno >= logging.WARNING else sys.stdout
            stream.write(f"{record.getMessage()}\n")
            stream.flush()
        except Exception:  # noqa: BLE001  (logging's contract: a handler reports its error, never raises)
            self.handleError(record)


class RunLogs(logging.Handler):
    """Appends each line about a run (:func:`about`) to that run's ``train.log``.

    Unless another handler of :data:`console` writes that file already (Hydra's job log, when the
    run trains in the Hydra job's folder). The file is opened for each line: a run has a handful.
    """

    def __init__(self, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self.setFormatter(logging.Formatter(LOG_FORMAT))

    def emit(self, record: logging.LogRecord) -> None:
        """Append ``record`` to ``<run_dir>/train.log`` if it names a run whose log no other handler writes."""
        run_dir = getattr(record, "run_dir", None)
        if run_dir is None:
            return
        try:
            path = os.path.realpath(Path(run_dir) / RUN_LOG)
            if any(os.path.realpath(getattr(h, "baseFilename", "")) == path for h in console.handlers):
                return
            with open(path, "a", encoding="utf-8") as log:
                log.write(f"{self.format(record)}\n")
        except Exception:  # noqa: BLE001  (logging's contract: a handler reports its error, never raises)
            self.handleError(record)


console.addHandler(Terminal())
console.setLevel(logging.INFO)
console.propagate = False  # root's handlers (Hydra's console) would show each line a second time


def keep_run_logs() -> None:
    """Give :data:`console` a :class:`RunLogs` (once): a command's runs keep their lines in their folders.

    ``drone-train`` calls it; a run trained from Python writes no log file. Hydra's job logging
    (``hydra/job_logging=drone``) sets :data:`console`'s handlers again, a :class:`RunLogs` among them.
    """
    if not any(isinstance(handler, RunLogs) for handler in console.handlers):
        console.addHandler(RunLogs())


class _PipeGuard:
    """A text stream that turns into :data:`os.devnull` when its reader is gone (EPIPE).

    Everything but ``write``, ``writelines`` and ``flush`` is the wrapped stream's.
    """

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream
        self._broken: TextIO | None = None

    def _gone(self) -> None:
        # The file descriptor itself points at devnull too: the interpreter's last flush of the
        # original stream, and child processes that inherit it, then write nowhere without error.
        try:
            fd = self._stream.fileno()
        except (AttributeError, ValueError, OSError):  # no descriptor (a test's captured stream)
            fd = None
        devnull = os.open(os.devnull, os.O_WRONLY)
        if fd is not None:
            os.dup2(devnull, fd)
        os.close(devnull)
        # The broken stream is kept: closing it (when nothing refers to it) would flush its buffer again.
        self._broken = self._stream
        self._stream = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115  (lives as long as the process)

    def _call(self, name: str, *args: Any) -> Any:
        try:
            return getattr(self._stream, name)(*args)
        except OSError as err:
            if err.errno != errno.EPIPE:  # a full disk behind a redirection is an error as before
                raise
            self._gone()
        return None

    def write(self, text: str) -> int:
        """Write ``text``; after the reader has gone, nowhere (returns ``len(text)`` then)."""
        written = self._call("write", text)
        return len(text) if written is None else written

    def writelines(self, lines: Any) -> None:
        """Write each of ``lines``."""
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        """Flush the stream (nothing, after the reader has gone)."""
        self._call("flush")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def guard_broken_pipes() -> None:
    """Wrap ``sys.stdout`` and ``sys.stderr`` so that a broken pipe never stops the command (once)."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if stream is not None and not isinstance(stream, _PipeGuard):
            setattr(sys, name, _PipeGuard(stream))
