"""One owner per run folder: an advisory lock held for the life of the process that trains it.

Two processes writing one run folder (a second terminal, a re-submitted job, a sweep re-run while
the first is alive) interleave their CSV rows and checkpoints without noticing. So the process that
trains a folder first takes ``fcntl.flock`` on ``<folder>/.lock`` and holds it until it ends; the
OS drops the lock when the process dies however it dies, so a killed run never blocks its resume.
The lock file says who holds it (host, pid, start time, SLURM job id): a second process is refused
with one line naming the owner.

Across hosts ``flock`` is only as good as the filesystem: local disks and NFSv4 pass it between
clients, Lustre only when mounted with ``-o flock``, some NFS setups not at all. So the owner also
renews the file's modification time while it trains (every flush, :func:`renew`), and a process on
another host that did get the ``flock`` still refuses while the owner's record is fresher than
:data:`STALE_AFTER_S`, unless it is the same SLURM job (a requeued job is the owner restarted: SLURM
never runs two instances of one job). A run killed on one node and resumed on another within that
time has to wait it out (the message says how long) or delete the lock file.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator
from pathlib import Path

from drone_torchrl.checks import ConfigError
from drone_torchrl.io.storage import writing

LOCK_NAME = ".lock"
#: How long an owner on another host counts as alive after it last renewed its lock. Runs renew it
#: at every flush (logger.flush_every_s, 10 s by default) and after every update call, so five
#: minutes is far past any pause of a live run (an evaluation with a video takes seconds).
STALE_AFTER_S = 300.0

# Open-file slots kept free beside the locks, for what a run opens meanwhile (its CSV and event
# file while flushing, a video, torch's and Python's own files).
SPARE_DESCRIPTORS = 256

# Folders this process holds: path -> the open descriptor carrying the lock (closing it releases it).
_HELD: dict[Path, int] = {}


class RunFolderBusy(ConfigError):
    """A run folder another live process owns: one line naming the folder and the owner."""


def _read_owner(fd: int) -> dict[str, object]:
    os.lseek(fd, 0, os.SEEK_SET)
    text = os.read(fd, 4096).decode("utf-8", "replace")
    try:
        owner = json.loads(text)
    except ValueError:
        return {}
    return owner if isinstance(owner, dict) else {}


def _describe(owner: dict[str, object]) -> str:
    if not owner:
        return "another process"
    return f"pid {owner.get('pid')} on {owner.get('host')} (since {owner.get('since')})"


def hold(folder: str | os.PathLike) -> Path:
    """Take ``folder``'s lock for this process (creating the folder), or raise :class:`RunFolderBusy`.

    Taking a folder this process already holds is a no-op. Returns the lock file's path.
    """
    folder = Path(folder).resolve()
    path = folder / LOCK_NAME
    if folder in _HELD:
        return path
    with writing(path):  # a read-only or full disk: one line, before the run writes anything else
        folder.mkdir(parents=True, exist_ok=True)
        # Read-only: a descriptor open for writing would keep the filesystem from being remounted
        # read-only; the record is written through a short-lived one below.
        _make_room()
        fd = os.open(path, os.O_RDONLY | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise
            raise RunFolderBusy(
                f"{folder} is in use by {_describe(_read_owner(fd))}: a run or sweep folder belongs to one "
                "process; wait for it to end, or stop it (kill -TERM writes a checkpoint) and run this again"
            ) from None
        owner = _read_owner(fd)
        age = time.time() - os.fstat(fd).st_mtime
        foreign = owner.get("host") not in (None, socket.gethostname())
        job, job_id = owner.get("slurm_job_id"), os.environ.get("SLURM_JOB_ID")
        same_job = job is not None and job == job_id
        if foreign and not same_job and age < STALE_AFTER_S:
            raise RunFolderBusy(
                f"{folder} is in use by {_describe(owner)}, renewed {age:.0f} s ago (this filesystem's flock "
                f"does not reach across hosts); if that process is gone, wait {STALE_AFTER_S - age:.0f} s or "
                f"delete {path}"
            )
        since = time.strftime("%Y-%m-%d %H:%M:%S")
        record = {"host": socket.gethostname(), "pid": os.getpid(), "since": since, "slurm_job_id": job_id}
        with writing(path):
            path.write_bytes(json.dumps(record).encode())
    except BaseException:
        os.close(fd)
        raise
    _HELD[folder] = fd
    return path


def _make_room() -> None:
    """Keep :data:`SPARE_DESCRIPTORS` open-file slots free beside the locks held.

    A population holds one lock per agent, and many systems start processes at a soft limit of 1024, so the
    soft limit is raised towards the hard one; past the hard one, one line says what to change.
    """
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    needed = len(_HELD) + 1 + SPARE_DESCRIPTORS
    if needed <= soft:
        return
    wanted = max(needed, 2 * soft)
    if hard != resource.RLIM_INFINITY:
        wanted = min(wanted, hard)
    if wanted < needed:
        raise ConfigError(
            f"cannot hold {len(_HELD) + 1} run folders in one process: the open-file limit is {hard} "
            "(ulimit -Hn); raise it, or train fewer agents per process (hydra.launcher.agents_per_job)"
        )
    resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))


@contextlib.contextmanager
def exclusive(path: str | os.PathLike) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``path`` (created if missing) for the ``with`` block.

    Waits while another process holds it. For a step two processes must not take at once (the
    first contact with a shared store, which creates its tables).
    """
    path = Path(path)
    with writing(path):
        fd = os.open(path, os.O_RDONLY | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def renew(folder: str | os.PathLike) -> None:
    """Refresh the owner's record time (what a process on another host reads as "alive")."""
    fd = _HELD.get(Path(folder).resolve())
    if fd is not None:
        with contextlib.suppress(OSError):  # a read-only or full disk: the write that fails next says so
            os.utime(fd)


def release(folder: str | os.PathLike) -> None:
    """Let go of ``folder`` (the file stays: deleting a lock file races with a process opening it)."""
    fd = _HELD.pop(Path(folder).resolve(), None)
    if fd is not None:
        os.close(fd)


def held() -> list[Path]:
    """The folders this process holds."""
    return list(_HELD)
