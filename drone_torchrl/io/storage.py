"""Writes the filesystem refuses (a full disk, a quota, a read-only or forbidden folder) as one line.

Python reports them as ``OSError`` from wherever the bytes were finally written, often without a
file name (a buffered write fails at ``close``). Every file a run writes goes through
:func:`writing`, which names the file, removes the temporary files of that write and raises
:class:`StorageError`; the commands print its one line with how to continue (the last complete
checkpoint and CSV are left as they were: every file is replaced atomically or appended to).
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

# What "the storage said no" looks like; any other OSError is a bug or a vanished file, not this.
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG})


class StorageError(OSError):
    """A file a run could not write: one line naming the file and the OS's reason."""

    def __init__(self, path: str | os.PathLike, reason: OSError) -> None:
        code = errno.errorcode.get(reason.errno or 0, str(reason.errno))
        super().__init__(reason.errno, f"cannot write {path}: {os.strerror(reason.errno or 0)} ({code})")
        self.path = Path(path)

    def __str__(self) -> str:
        return str(self.args[1])


def folder_refuses(folder: Path, size: int) -> int | None:
    """Why ``folder`` would refuse ``size`` more bytes (the errno), or None: for a child process's
    failed write (ffmpeg's reaches Python as a broken pipe), diagnosed after the fact."""
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


def is_storage_error(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in STORAGE_ERRNOS


@contextmanager
def writing(path: str | os.PathLike, *temporary: str | os.PathLike) -> Iterator[None]:
    """Run a write of ``path``; a refused write becomes :class:`StorageError` after ``temporary``
    files (this write's half-written ones) are removed."""
    try:
        yield
    except StorageError:
        raise
    except OSError as err:
        if err.errno not in STORAGE_ERRNOS:
            raise
        for tmp in temporary:
            # A read-only folder keeps it; the next successful write replaces it.
            with contextlib.suppress(OSError):
                Path(tmp).unlink(missing_ok=True)
        raise StorageError(path, err) from None
