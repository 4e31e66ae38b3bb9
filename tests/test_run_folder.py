"""A run folder belongs to one process; signals stop a run with a checkpoint; a refused write is one line.

- Two processes on one run folder: the second is refused in one line naming the owner's pid, and the
  first one's CSV holds every episode exactly once. The same for a sweep started twice at once.
- SIGTERM (what SLURM sends before a time limit) and SIGUSR1 stop training after the update in
  flight with a checkpoint; resuming then trains each episode exactly once (episodes 0..N-1, no
  row twice, none missing).
- A full disk (a small tmpfs filled up) and a read-only one (the tmpfs remounted read-only; these
  tests run as root, where permission bits cannot make a write fail) at each kind of write: the
  CSV, TensorBoard, a checkpoint, a video, ``FAILED.txt``. Each stops the run with one line naming
  the file and leaves no temporary file; after the disk is repaired the run resumes to episodes
  0..N-1 exactly once.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

from drone_torchrl.apps import train as train_app
from drone_torchrl.config import config_dir
from drone_torchrl.io import run_lock
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.io.storage import StorageError
from drone_torchrl.training import run as run_module
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.signals import TrainingStopped
from drone_torchrl.training.trainer import Trainer, train_jobs

QUICK = ["eval.video=false", "eval.every_episodes=0", "progress=false", "env.max_steps=50"]


def _cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=[*QUICK, *overrides])


def _episodes(run_dir: Path) -> list[int]:
    rows, _ = read_episodes(run_dir / "episodes.csv")
    return [int(e) for e in rows["episode"]]


def _rows(run_dir: Path) -> int:
    """Rows in the CSV as written (read_episodes keeps one per episode; a row written twice counts twice)."""
    return len((run_dir / "episodes.csv").read_text().strip().splitlines()) - 1


def _drone_train(*args: str, cwd: Path, wait: bool = True) -> subprocess.Popen | subprocess.CompletedProcess:
    command = [sys.executable, "-m", "drone_torchrl.apps.train", *args]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    if wait:
        return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=cwd, env=env)
    return subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env
    )


def _wait_for_owner(folder: Path, pid: int, proc: subprocess.Popen, also: str | None = None) -> None:
    """Until ``folder``'s lock names ``pid`` (and a file matching the glob ``also`` exists in it):
    the owner is training."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        try:
            owner = json.loads((folder / run_lock.LOCK_NAME).read_text())
        except (OSError, ValueError):
            owner = {}
        if owner.get("pid") == pid and (also is None or any(folder.glob(also))):
            return
        time.sleep(0.2)
    raise AssertionError(f"{folder} was never locked by {pid}")


def _one_error_line(stderr: str, *words: str) -> str:
    assert "Traceback" not in stderr, stderr
    errors = [line for line in stderr.splitlines() if "error" in line]
    assert len(errors) == 1, stderr
    for word in words:
        assert word in errors[0], stderr
    return errors[0]


# ---------------------------------------------------------------------------------------- the lock


def test_a_folder_is_held_once_and_let_go(tmp_path):
    folder = tmp_path / "run"
    path = run_lock.hold(folder)
    assert run_lock.hold(folder) == path  # this process again: a no-op
    owner = json.loads(path.read_text())
    assert owner["pid"] == os.getpid()
    # Another process cannot flock it while this one holds it, and can once it is let go.
    flock = (
        f"import fcntl, os; fcntl.flock(os.open({str(path)!r}, os.O_RDONLY), fcntl.LOCK_EX | fcntl.LOCK_NB)"
    )
    busy = subprocess.run([sys.executable, "-c", flock], capture_output=True, text=True)
    assert busy.returncode != 0 and "BlockingIOError" in busy.stderr
    run_lock.release(folder)
    assert subprocess.run([sys.executable, "-c", flock], capture_output=True, text=True).returncode == 0


def test_a_population_holds_more_folders_than_the_soft_open_file_limit(tmp_path):
    """One lock per agent: with a soft limit of 300 (many systems start at 1024), holding 400
    folders raises it towards the hard limit, keeping SPARE_DESCRIPTORS free."""
    import resource

    if resource.getrlimit(resource.RLIMIT_NOFILE)[1] < 400 + run_lock.SPARE_DESCRIPTORS:
        pytest.skip("this machine's hard open-file limit is below what the test needs")
    code = (
        "import resource\n"
        "from drone_torchrl.io import run_lock\n"
        "resource.setrlimit(resource.RLIMIT_NOFILE, (300, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))\n"
        f"for i in range(400): run_lock.hold({str(tmp_path)!r} + f'/job{{i}}')\n"
        "print(len(run_lock.held()), resource.getrlimit(resource.RLIMIT_NOFILE)[0])\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    held, soft = map(int, proc.stdout.split())
    assert held == 400 and soft >= 400 + run_lock.SPARE_DESCRIPTORS


def test_an_owner_on_another_host_is_honoured_while_it_renews_its_lock(tmp_path, monkeypatch):
    """Where flock does not reach across hosts, the record still refuses while it is fresh, but not
    once it is older than STALE_AFTER_S, nor for the same SLURM job (a requeue)."""
    folder = tmp_path / "run"
    folder.mkdir()
    lock = folder / run_lock.LOCK_NAME
    lock.write_text(json.dumps({"host": "node-7", "pid": 4242, "since": "x", "slurm_job_id": "99"}))
    with pytest.raises(run_lock.RunFolderBusy, match="pid 4242 on node-7"):
        run_lock.hold(folder)
    monkeypatch.setenv("SLURM_JOB_ID", "99")
    run_lock.hold(folder)  # the same job, requeued: its earlier self is gone
    run_lock.release(folder)
    monkeypatch.setenv("SLURM_JOB_ID", "100")
    lock.write_text(json.dumps({"host": "node-7", "pid": 4242, "since": "x", "slurm_job_id": "99"}))
    stale = time.time() - run_lock.STALE_AFTER_S - 1
    os.utime(lock, (stale, stale))
    run_lock.hold(folder)  # not renewed for longer than STALE_AFTER_S: the owner is gone
    assert json.loads(lock.read_text())["pid"] == os.getpid()
    run_lock.release(folder)


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_two_processes_on_one_run_folder_then_sigterm_and_resume(tmp_path, command_here):
    """The second process (same folder, or resume of it) is refused in one line naming the owner's
    pid; SIGTERM then stops the owner with a checkpoint (exit 143); its CSV holds episodes
    0..E-1 exactly once, and the resume trains E..N-1: no episode twice, none lost.

    The two refused commands run in this process (another one than the owner's; they are refused
    before any work, so a new process would only add its imports); a small budget, so that one
    let through fails at once instead of training for minutes."""
    run = tmp_path / "run"
    common = [*QUICK, f"hydra.run.dir={run}"]
    owner = _drone_train(*common, "algo.episodes=1000000", cwd=tmp_path, wait=False)
    try:
        # Its first checkpoint too: a folder without one is refused as no run to resume, before its owner.
        _wait_for_owner(run, owner.pid, owner, also="checkpoints/last.pt")
        second = command_here(train_app.run, "drone-train", *common, "algo.episodes=2", cwd=tmp_path)
        assert second.returncode == 1
        _one_error_line(second.stderr, str(run), f"pid {owner.pid}")
        resumed = command_here(train_app.run, "drone-train", "progress=false", f"resume={run}", cwd=tmp_path)
        assert resumed.returncode == 1
        _one_error_line(resumed.stderr, f"pid {owner.pid}")
        assert not (tmp_path / "outputs").exists()  # the refused resume left no folder of its own
        time.sleep(1.0)
        owner.send_signal(signal.SIGTERM)
        _, stderr = owner.communicate(timeout=120)
    finally:
        owner.kill()
    assert owner.returncode == 128 + signal.SIGTERM, stderr
    assert "stopped by SIGTERM; checkpoint written for 1 run(s)" in stderr and f"resume={run}" in stderr
    done = load_checkpoint(run / "checkpoints" / "last.pt")["episodes_done"]
    assert done > 0 and _episodes(run) == list(range(done)) and _rows(run) == done
    budget = done + 300
    again = _drone_train("progress=false", f"resume={run}", f"algo.episodes={budget}", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert f"continuing from episode {done} (the checkpoint's); 0 episode(s) logged after it" in again.stdout
    assert _episodes(run) == list(range(budget)) and _rows(run) == budget


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGUSR1])
def test_a_signal_stops_a_population_after_the_update_with_checkpoints(tmp_path, signum, monkeypatch):
    """In process: the signal arrives while update 37 is booked; training stops after that call
    with every agent's checkpoint at the episodes its CSV holds, and resuming completes 0..N-1."""
    from drone_torchrl.training import trainer as trainer_module

    monkeypatch.setattr(trainer_module, "MAX_UPDATES_PER_CALL", 10)  # calls of 10 updates: 31..40
    budget = 400
    dirs = [tmp_path / f"agent{s}" for s in range(2)]
    cfgs = [_cfg(f"algo.episodes={budget}", f"seed={s}") for s in range(2)]
    record = run_module.RunRecord.record
    before = signal.getsignal(signum)

    def record_and_signal(self, episodes, metrics):
        record(self, episodes, metrics)
        if self.updates_done == 37:
            os.kill(os.getpid(), signum)

    run_module.RunRecord.record = record_and_signal
    try:
        with pytest.raises(TrainingStopped) as stopped:
            Trainer([prepare(cfg, d) for cfg, d in zip(cfgs, dirs, strict=True)]).train()
    finally:
        run_module.RunRecord.record = record
        for d in dirs:
            run_lock.release(d)
    assert stopped.value.exit_code == 128 + signum and stopped.value.run_dirs == dirs
    assert signal.getsignal(signum) == before  # the handler in place before training is back
    for d in dirs:
        # One episode per update, ten updates per call: the call in flight (31..40) is finished.
        assert load_checkpoint(d / "checkpoints" / "last.pt")["episodes_done"] == 40
        assert _episodes(d) == list(range(40))
    outcomes = train_jobs(
        [prepare(_cfg(f"algo.episodes={budget}", f"seed={s}"), d) for s, d in enumerate(dirs)]
    )
    assert all(o.error is None for o in outcomes)
    for d in dirs:
        assert _episodes(d) == list(range(budget)) and _rows(d) == budget


@pytest.mark.slow
def test_the_same_sweep_started_twice_at_once(tmp_path):
    """The second sweep process is refused in one line before it writes; the first finishes every
    job with every episode exactly once."""
    args = ["-m", "seed=0,1", "hydra/launcher=fused", "algo.episodes=60000", *QUICK, "sweep_name=twice"]
    first = _drone_train(*args, cwd=tmp_path, wait=False)
    sweep = tmp_path / "multirun" / "twice"
    try:
        _wait_for_owner(sweep, first.pid, first, also="*seed=1/episodes.csv")
        second = _drone_train(*args, cwd=tmp_path)
        assert second.returncode == 1
        _one_error_line(second.stderr, str(sweep), f"pid {first.pid}")
        stdout, stderr = first.communicate(timeout=600)
    finally:
        first.kill()
    assert first.returncode == 0, stderr
    jobs = sorted(p.parent for p in sweep.glob("*/episodes.csv"))
    assert [job.name.rsplit(",", 1)[-1] for job in jobs] == ["seed=0", "seed=1"]
    for job in jobs:
        assert _episodes(job) == list(range(60000)) and _rows(job) == 60000


# ------------------------------------------------------------------------------------- storage errors


@pytest.fixture
def small_disk(tmp_path):
    """A 64 MiB tmpfs of its own (root only), unmounted afterwards."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    made = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64m", "tmpfs", str(mount)], capture_output=True
    )
    if made.returncode != 0:
        pytest.skip(f"this machine does not allow a tmpfs mount: {made.stderr.decode().strip()}")
    yield mount
    subprocess.run(["umount", "-l", str(mount)], check=False)


class Disk:
    """Breaks the tmpfs (filled up, or remounted read-only) and repairs it. ``room``: bytes left free
    when filling it up (rounded to pages), for writes that start and then run out of space."""

    def __init__(self, mount: Path, how: str, room: int = 0) -> None:
        self.mount, self.how, self.room, self.broken = mount, how, room, False

    def break_(self) -> None:
        if self.broken:
            return
        self.broken = True
        if self.how == "read-only":
            subprocess.run(["mount", "-o", "remount,ro", str(self.mount)], check=True)
            return
        reserve = self.mount / "reserve"
        reserve.write_bytes(b"\0" * self.room)  # freed once the rest is full
        chunk = b"\0" * (1 << 20)
        with open(self.mount / "filler", "wb", buffering=0) as f:  # nothing left to flush at close
            try:
                while True:
                    f.write(chunk)
            except OSError as err:
                assert err.errno == errno.ENOSPC
                # What is left is less than a page per file: fill it byte by byte.
                with open(self.mount / "filler2", "wb", buffering=0) as g:
                    try:
                        while True:
                            g.write(b"\0" * 512)
                    except OSError:
                        pass
        reserve.unlink()

    def repair(self) -> None:
        if self.how == "read-only":
            subprocess.run(["mount", "-o", "remount,rw", str(self.mount)], check=True)
        else:
            for name in ("filler", "filler2"):
                (self.mount / name).unlink(missing_ok=True)
        self.broken = False


# Where each kind of write happens: (object, attribute) patched to break the disk first.
WRITES = {
    "csv": ("drone_torchrl.io.episodes_csv.EpisodeCSV", "flush", "episodes.csv"),
    "tensorboard": ("drone_torchrl.loggers.tb_logger.RunLogger", "flush", "events.out.tfevents"),
    "checkpoint": ("drone_torchrl.training.run", "save_checkpoint", "last.pt"),
    "video": ("drone_torchrl.training.run", "save_mp4", ".mp4"),
    "failed": ("drone_torchrl.training.run.RunRecord", "fail", "FAILED.txt"),
}


def _target(dotted: str):
    import importlib

    module, _, name = dotted.rpartition(".")
    try:
        return importlib.import_module(dotted)
    except ImportError:
        return getattr(importlib.import_module(module), name)


@pytest.mark.parametrize("how", ["full", "read-only"])
@pytest.mark.parametrize("kind", list(WRITES))
def test_a_refused_write_is_one_line_and_the_run_resumes(small_disk, kind, how, monkeypatch):
    run = small_disk / "run"
    disk = Disk(small_disk, how)
    dotted, attribute, named = WRITES[kind]
    owner = _target(dotted)
    original = getattr(owner, attribute)
    calls = {"n": 0}

    def broken_then_original(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] >= (1 if kind == "failed" else 2):  # the second write of its kind: the run is under way
            disk.break_()
        return original(*args, **kwargs)

    monkeypatch.setattr(owner, attribute, broken_then_original)
    video = "true" if kind == "video" else "false"
    overrides = ("algo.episodes=600", "checkpoint.every_episodes=100", f"eval.video={video}")
    if kind == "video":
        overrides += ("eval.every_episodes=200", "logger.video_stride=3")
    if kind == "failed":  # the run diverges at episode 200 (its weights turn NaN): FAILED.txt is due
        overrides += ("checkpoint.every_episodes=200",)
    trainer = Trainer([prepare(_cfg(*overrides), run)])
    try:
        with pytest.raises(StorageError) as refused:
            if kind == "failed":
                trainer.step([0], 200)
                with torch.no_grad():
                    trainer.population.policy.params.get(("mean", "bias"))[0] = float("nan")
            trainer.train()
    finally:
        run_lock.release(run)
    message = str(refused.value)
    assert "\n" not in message and named in message and str(run) in message
    reason = "No space left on device (ENOSPC)" if how == "full" else "Read-only file system (EROFS)"
    assert reason in message
    disk.repair()
    assert not list(run.rglob("*.tmp")) and not list(run.rglob("*.part.*"))
    monkeypatch.setattr(owner, attribute, original)
    before = load_checkpoint(run / "checkpoints" / "last.pt")["episodes_done"]
    (outcome,) = train_jobs([prepare(_cfg(*overrides[:2], "eval.video=false"), run)])
    assert outcome.error is None, outcome.error
    assert before > 0 and _episodes(run) == list(range(600)) and _rows(run) == 600
