"""Writes the filesystem refuses (full disk, quota, read-only, name too long) as one line.

Read-only covers a forbidden folder too. This is the one module every command (drone-train,
drone-eval, drone-export, drone-report) writes its files through.

Python reports them as ``OSError`` from wherever the bytes were finally written, often without a
file name (a buffered write fails at ``close``). Every file a command writes goes through
:func:`writing`, which names the file, removes the temporary files of that write and raises
:class:`StorageError`; the commands print its one line with how to continue (the last complete
checkpoint and CSV are left as they were: every file is replaced atomically
(:func:`write_atomically`) or appended to).

Paths the user names (a run folder, an output file) are checked before any work by
:func:`name_too_long`: each component against the file system's ``NAME_MAX``, the whole path
against its ``PATH_MAX``. A name that still reaches the file system too long (a file a command names
inside such a folder) is refused by :func:`writing` like a full disk.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import os
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

# What "the storage said no" looks like; any other OSError is a bug or a vanished file, not this.
STORAGE_ERRNOS = frozenset(
    {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG, errno.ENAMETOOLONG}
)
# Linux's NAME_MAX and PATH_MAX (limits.h), in bytes: for a file system that does not say (pathconf fails).
DEFAULT_NAME_MAX = 255
DEFAULT_PATH_MAX = 4096
# Characters of an overlong name shown in a message (the rest is elided).
NAME_SHOWN = 24


class StorageError(OSError):
    """A file a run could not write: one line naming the file and the OS's reason.

    Args:
        path: the file that could not be written.
        reason: the OS's refusal (its errno names the reason).
    """

    def __init__(self, path: str | os.PathLike, reason: OSError) -> None:
        code = errno.errorcode.get(reason.errno or 0, str(reason.errno))
        super().__init__(reason.errno, f"cannot write {path}: {os.strerror(reason.errno or 0)} ({code})")
        self.path = Path(path)

    def __str__(self) -> str:
        return str(self.args[1])


def folder_refuses(folder: Path, size: int) -> int | None:
    """Why ``folder`` would refuse ``size`` more bytes (the errno), or None.

    For a child process's failed write (ffmpeg's reaches Python as a broken pipe), diagnosed after the fact.
    """
    try:
        stats = os.statvfs(folder)
    except OSError:
        return None
    if stats.f_flag & os.ST_RDONLY:
        return errno.EROFS
    if not os.access(folder, os.W_OK):
        return errno.EACCES
    if stats.f_bavail * stats.f_frsize < size:
        return errno.ENOSPC
    return None


@contextmanager
def writing(path: str | os.PathLike, *temporary: str | os.PathLike) -> Iterator[None]:
    """Run a write of ``path``; a refused write becomes :class:`StorageError`.

    ``temporary`` files (this write's half-written ones) are removed whenever the write does not finish:
    refused, or stopped by another exception (a signal turned into one, Ctrl-C).
    """
    try:
        yield
    except BaseException as err:
        for tmp in temporary:
            # A read-only folder keeps it; the next successful write replaces it.
            with contextlib.suppress(OSError):
                Path(tmp).unlink(missing_ok=True)
        if isinstance(err, StorageError) or not (isinstance(err, OSError) and err.errno in STORAGE_ERRNOS):
            raise
        raise StorageError(path, err) from None  # type: ignore[arg-type]


def write_atomically(path: str | os.PathLike, data: bytes | bytearray | memoryview) -> Path:
    """Write ``data`` to ``path`` atomically, through ``<path>.tmp`` and a rename.

    The folder is made if missing. A reader, or a process killed meanwhile, sees the old file or
    the whole new one, never a part. A refused write is :class:`StorageError` and leaves no
    temporary file.
    """
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with writing(path, tmp):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(data)
        os.replace(tmp, path)
    return path


def write_csv(path: str | os.PathLike, header: Sequence[Any], rows: Iterable[Sequence[Any]]) -> Path:
    """Write a CSV file of ``header`` and ``rows`` (:mod:`csv`'s dialect) atomically (:func:`write_atomically`)."""
    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(header)
    writer.writerows(rows)
    return write_atomically(path, text.getvalue().encode())


def new_figure(figsize: tuple[float, float]) -> Any:
    """A matplotlib figure of ``figsize`` inches on the Agg canvas (no pyplot), for :func:`write_figure`."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


def write_figure(fig: Any, path: str | os.PathLike, **savefig: Any) -> Path:
    """Save a matplotlib figure as ``path`` atomically (its suffix names the format).

    Atomically because matplotlib writes straight into the file, so a full disk would leave a
    partial image.
    """
    buffer = io.BytesIO()
    fig.savefig(buffer, format=Path(path).suffix.lstrip(".") or None, **savefig)
    return write_atomically(path, buffer.getbuffer())


def _limit(folder: Path, name: str, default: int) -> int:
    try:
        return os.pathconf(folder, name)
    except (OSError, ValueError):
        return default


def name_too_long(path: str | os.PathLike) -> str | None:
    """Why the file system would refuse ``path`` as too long (ENAMETOOLONG), or None.

    Each component against ``NAME_MAX`` and the whole path against ``PATH_MAX`` of the nearest existing folder
    above it (the folders still to be made are on its file system). In bytes, as the file system counts.
    """
    path = Path(path).expanduser()
    absolute = path.absolute()
    existing = _nearest_existing(absolute.parent)
    name_max = _limit(existing, "PC_NAME_MAX", DEFAULT_NAME_MAX)
    for part in path.parts:
        size = len(os.fsencode(part))
        if size > name_max and part != path.anchor:
            shown = part if len(part) <= NAME_SHOWN else part[:NAME_SHOWN] + "..."
            return f"its name {shown!r} is {size} bytes long; this file system allows {name_max}"
    path_max = _limit(existing, "PC_PATH_MAX", DEFAULT_PATH_MAX)
    size = len(os.fsencode(absolute))
    if size >= path_max:  # PATH_MAX counts the terminating NUL
        return f"it is {size} bytes long as an absolute path; this file system allows {path_max - 1}"
    return None


def unwritable(folder: str | os.PathLike, room: int = 1) -> str | None:
    """Why nothing could be written into ``folder`` (made if missing), told before any work, or None.

    A name too long (:func:`name_too_long`), a file where a folder must be, or the nearest existing folder
    read-only, forbidden or with less than ``room`` bytes free (:func:`folder_refuses`). A write that fails
    all the same is still refused in one line by :func:`writing`.
    """
    too_long = name_too_long(folder)
    if too_long is not None:
        return too_long
    existing = _nearest_existing(Path(folder).expanduser().absolute())
    if not existing.is_dir():
        return f"{existing} is a file"
    refused = folder_refuses(existing, room)
    if refused == errno.ENOSPC and room > 1:
        return f"{existing} has less than {room} bytes free"
    if refused is not None:
        return f"{existing}: {os.strerror(refused)} ({errno.errorcode[refused]})"
    return None


def _nearest_existing(path: Path) -> Path:
    """``path`` or the nearest folder above it that exists."""
    while path != path.parent:
        try:
            if path.exists():
                break
        except OSError:  # a component too long, or not a folder: not an existing folder
            pass
        path = path.parent
    return path
