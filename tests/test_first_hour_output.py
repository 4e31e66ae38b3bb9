"""What a new user sees and keeps: output piped into ``head`` never fails a run, each run's log file holds
what the terminal showed, and ``drone-train`` ends with the commands that look at what it made.

The closed-pipe tests run the installed commands with their stdout's reading end closed at once
(``drone-train ... | head -0``): every write to it fails with EPIPE.
"""

import errno
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from drone_torchrl.apps import evaluate as eval_app
from drone_torchrl.apps import train as train_app
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.training.jobs import job_status

TINY = [
    "algo.episodes=2",
    "env.max_steps=20",
    "eval.episodes=1",
    "eval.video=false",
    "progress=false",
    "checkpoint.every_episodes=1",
]
ENV = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}


def _into_closed_pipe(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """``drone-train args...`` whose stdout's reader has gone before it writes anything."""
    command = Path(sys.executable).parent / "drone-train"
    if not command.exists():
        pytest.skip("console scripts are not installed in this environment")
    proc = subprocess.Popen(
        [str(command), *args], cwd=cwd, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    proc.stdout.close()
    err = proc.stderr.read()
    proc.stderr.close()
    return subprocess.CompletedProcess(proc.args, proc.wait(timeout=300), "", err)


def _jobs(sweep: Path) -> list[Path]:
    return sorted(p for p in sweep.iterdir() if p.is_dir())


# Slow stage: a real sweep process (several seconds of imports per job); the default suite stays near 5 minutes.
@pytest.mark.slow
def test_a_sweep_into_a_closed_pipe_trains_and_fails_no_job(tmp_path, command_here):
    """Piped into ``head``, a sweep trains every job, and its re-run finds them finished: no FAILED.txt."""
    sweep = tmp_path / "sweep"
    first = command_here(
        train_app.run, "drone-train", "-m", "seed=0,1", f"hydra.sweep.dir={sweep}", *TINY, cwd=tmp_path
    )
    assert first.returncode == 0, first.stderr
    # One job trained, two already finished.
    proc = _into_closed_pipe(tmp_path, "-m", "seed=0,1,2", f"hydra.sweep.dir={sweep}", *TINY)
    assert proc.returncode == 0, proc.stderr
    assert "BrokenPipe" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert sorted(p.parent.name for p in sweep.glob("*/FAILED.txt")) == []
    assert len(_jobs(sweep)) == 3
    for job in _jobs(sweep):
        assert job_status(job) == ("finished", "2 episodes, final running-mean return " + _final(job))


def _final(job: Path) -> str:
    return f"{load_checkpoint(job / 'checkpoints' / 'last.pt')['final']['final_return']:.1f}"


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_a_run_into_a_closed_pipe_exits_0_with_its_final_checkpoint(tmp_path):
    """``drone-train ... | head -0`` trains to the end, exits 0, and its folder is a finished run's."""
    run = tmp_path / "run"
    proc = _into_closed_pipe(tmp_path, f"hydra.run.dir={run}", *TINY)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    ckpt = load_checkpoint(run / "checkpoints" / "last.pt")
    assert ckpt["episodes_done"] == 2 and ckpt["final"] is not None
    assert not (run / "FAILED.txt").exists()
    # What the terminal would have shown is in the run's log all the same.
    log = (run / "train.log").read_text()
    assert f"{run}: 2 episodes, running-mean(100) return {ckpt['final']['final_return']:.1f}" in log


# Slow stage: a real sweep process (several seconds of imports per job); the default suite stays near 5 minutes.
@pytest.mark.slow
def test_a_job_that_fails_with_stdout_closed_is_failed_and_the_sweep_exits_nonzero(tmp_path):
    """A job that really fails (its checkpoints folder is a file) is the one failed job, stdout closed or not."""
    sweep = tmp_path / "sweep"
    (sweep / "job_1").mkdir(parents=True)
    (sweep / "job_1" / "checkpoints").write_text("not a folder")
    proc = _into_closed_pipe(
        tmp_path,
        "-m",
        "seed=0,1",
        f"hydra.sweep.dir={sweep}",
        "hydra.sweep.subdir=job_${hydra.job.num}",
        *TINY,
    )
    assert proc.returncode != 0
    assert "drone-train: 1 job(s) failed" in proc.stderr, proc.stderr
    assert sorted(p.parent.name for p in sweep.glob("*/FAILED.txt")) == ["job_1"]
    assert "checkpoints" in (sweep / "job_1" / "FAILED.txt").read_text()
    assert job_status(sweep / "job_0")[0] == "finished"


def test_the_run_log_holds_what_the_terminal_showed_and_the_next_steps(tmp_path, command_here):
    """train.log holds each line drone-train printed (its final summary, its next steps), which name
    the real run folder and its last checkpoint."""
    proc = command_here(train_app.run, "drone-train", "hydra.run.dir=run", *TINY, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    run = tmp_path / "run"
    lines = proc.stdout.splitlines()
    final = load_checkpoint(run / "checkpoints" / "last.pt")["final"]
    assert f"{run}: 2 episodes, running-mean(100) return {final['final_return']:.1f}" in lines[0]
    assert lines[-3:] == [
        "next steps:",
        "  tensorboard --logdir run",
        "  drone-eval checkpoint=run/checkpoints/last.pt",
    ]
    assert list((tmp_path / "run").rglob("events.out.tfevents.*"))  # what the tensorboard line names
    log = (run / "train.log").read_text()
    for line in lines:
        assert line in log
    assert "[INFO]" not in proc.stdout  # the terminal shows the text alone, as before

    # Resumed in its own folder (Hydra's job log is a new folder's, removed): the run's log all the same.
    again = command_here(
        train_app.run, "drone-train", "resume=run", "algo.episodes=3", "progress=false", cwd=tmp_path
    )
    assert again.returncode == 0, again.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    log = (run / "train.log").read_text()
    assert f"{run}: continuing from episode 2 (the checkpoint's)" in log
    assert f"{run}: 3 episodes, running-mean(100) return" in log
    assert log.count("next steps:") == 2


@pytest.mark.parametrize("launcher", ["basic", "fused"])
def test_a_sweep_ends_with_the_report_of_its_folder(tmp_path, command_here, launcher):
    """After a sweep: drone-report and TensorBoard on the sweep's folder; each job's log holds its own
    summary (the fused launcher's jobs too, trained together in one process)."""
    proc = command_here(
        train_app.run,
        "drone-train",
        "-m",
        "seed=0,1",
        "hydra.sweep.dir=sw",
        f"hydra/launcher={launcher}",
        *TINY,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-3:] == ["next steps:", "  drone-report sw", "  tensorboard --logdir sw"]
    jobs = _jobs(tmp_path / "sw")
    assert len(jobs) == 2
    for job in jobs:
        log = (job / "train.log").read_text()
        assert re.search(rf"{re.escape(str(job))}: 2 episodes, running-mean\(100\) return", log), log
        other = next(j for j in jobs if j != job)
        assert f"{other}:" not in log


def test_the_eval_log_holds_the_table(tmp_path, command_here):
    proc = command_here(
        eval_app.run,
        "drone-eval",
        "episodes=2",
        "env.max_steps=20",
        "video=false",
        "plot=false",
        "hydra.run.dir=ev",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "PD controller: return" in proc.stdout
    log = (tmp_path / "ev" / "evaluate.log").read_text()
    for line in proc.stdout.splitlines():
        assert line in log


def test_the_guard_drops_a_broken_pipe_and_nothing_else():
    """EPIPE turns the stream into devnull (the next writes go nowhere, without error); a full disk
    behind a redirection is still an error."""
    from drone_torchrl.io.streams import _PipeGuard

    read, write = os.pipe()
    os.close(read)
    guard = _PipeGuard(os.fdopen(write, "w"))
    assert guard.write("lost\n") == 5
    guard.flush()  # EPIPE here: from now on, devnull
    assert guard.write("also lost\n") == 10
    guard.flush()
    assert os.path.samestat(os.fstat(write), os.stat(os.devnull))  # the descriptor too

    class FullDisk(io.StringIO):
        def write(self, text: str) -> int:
            raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match="No space left"):
        _PipeGuard(FullDisk()).write("x")


def test_a_logging_config_that_disables_loggers_does_not_silence_the_run_lines(capsys):
    """hydra/job_logging=disabled (drone-export's) disables every existing logger: the run's lines
    (its output, not diagnostics) still show."""
    import logging.config

    from drone_torchrl.io.streams import console

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    before = {
        name: lg.disabled
        for name, lg in logging.Logger.manager.loggerDict.items()
        if isinstance(lg, logging.Logger)
    }
    try:
        logging.config.dictConfig(
            {"version": 1, "root": {"level": "ERROR"}, "disable_existing_loggers": True}
        )
        console.info("the summary")
        console.warning("a note")
    finally:
        for name, disabled in before.items():
            logging.getLogger(name).disabled = disabled
        root.handlers[:] = handlers
        root.setLevel(level)
    assert capsys.readouterr() == ("the summary\n", "a note\n")
