"""Sweeps on a real SLURM scheduler (``hydra/launcher=slurm``): submission, requeue on timeout, scancel.

Marked ``slurm``: they need a running one-node cluster (``bash .ci/slurm.sh start`` as root; ``.ci/run``
runs them as a stage after the default suite) and skip, with the reason, where there is none.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from drone_torchrl.io.episodes_csv import read_episodes

pytestmark = pytest.mark.slurm

UNAVAILABLE = Path(os.environ.get("DRONE_SLURM_DIR", "/tmp/drone-slurm")) / "unavailable"
BIN = Path(sys.executable).parent
QUICK = ["eval.video=false", "progress=false", "eval.every_episodes=0"]


def _cluster_reason() -> str | None:
    if UNAVAILABLE.is_file():
        return f"no SLURM cluster: {UNAVAILABLE.read_text().strip()}"
    if shutil.which("sinfo") is None:
        return "no SLURM cluster: sinfo not found (start one as root with: bash .ci/slurm.sh start)"
    up = subprocess.run(["sinfo", "-h", "-o", "%T"], capture_output=True, text=True)
    if up.returncode or not re.search(r"idle|mixed|allocated", up.stdout):
        return f"no SLURM cluster answering sinfo ({(up.stderr or up.stdout).strip()[:200]})"
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="needs the submitit extra")
    return None


@pytest.fixture(scope="module", autouse=True)
def cluster(request):
    if "slurm" not in (request.config.option.markexpr or ""):
        pytest.skip("SLURM tests run as their own stage: python -m pytest -m slurm (see .ci/run)")
    reason = _cluster_reason()
    if reason:
        pytest.skip(reason)


def _train(sweep: Path, *overrides: str, wait: bool = True, launcher: str = "slurm"):
    cmd = [
        str(BIN / "drone-train"),
        "-m",
        f"hydra/launcher={launcher}",
        f"hydra.sweep.dir={sweep}",
        *QUICK,
        *overrides,
    ]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


def _sacct(job_id: str, tasks: int, settle_s: float = 60.0) -> dict[str, str]:
    """``{"12_0": "COMPLETED", ...}``: SLURM's accounting record of an array job's tasks.

    submitit sees a task's result file before slurmd has told the controller the task ended, so
    a task can still read RUNNING (or COMPLETING) for a moment after the sweep returns, and
    slurmdbd may not have recorded a finished task at all yet (sacct then lists fewer tasks):
    wait until all ``tasks`` are listed and none is still pending or running."""
    deadline = time.time() + settle_s
    while True:
        out = subprocess.run(
            ["sacct", "-X", "-n", "-P", "-o", "JobID,State", "-j", job_id],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        states = dict(line.split("|")[:2] for line in out.split() if line)
        settled = len(states) >= tasks and not {"PENDING", "RUNNING", "COMPLETING"} & set(states.values())
        if settled or time.time() > deadline:
            return states
        time.sleep(1)


def _job_id(output: str) -> str:
    return re.search(r"Submitted SLURM job\(s\) (\d+)", output).group(1)


def test_a_sweep_runs_as_slurm_jobs_and_reports(tmp_path):
    sweep = tmp_path / "sweep"
    done = _train(sweep, "seed=0,1,2", "algo.episodes=6")
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-3000:]
    job = _job_id(output)
    # The scheduler's view: three array tasks of one job, all completed.
    assert _sacct(job, 3) == {f"{job}_{i}": "COMPLETED" for i in range(3)}
    shown = subprocess.run(
        ["scontrol", "show", "job", job], capture_output=True, text=True, check=True
    ).stdout
    assert shown.count("JobState=COMPLETED") == 3
    assert "sacct" not in output.lower()  # accounting answers: no polling warnings
    assert "3 finished, 0 failed" in output
    report = subprocess.run([str(BIN / "drone-report"), str(sweep)], capture_output=True, text=True)
    assert report.returncode == 0, report.stderr
    assert "3 runs in 1 settings" in report.stdout or "3 runs" in report.stdout
    for seed in range(3):
        (episodes, _) = read_episodes(next(sweep.glob(f"*seed={seed}")) / "episodes.csv")
        assert episodes["episode"].tolist() == list(range(6))


def test_a_job_past_its_time_limit_is_requeued_and_continues(tmp_path):
    """A job with one minute of SLURM time and far more episodes than fit in it: submitit requeues it
    when SLURM signals the limit (10 s before it; slurmctld checks limits every 30 s, so the signal
    comes 20-50 s into the run), and the requeued job continues from its last checkpoint (every 100
    episodes). SLURM holds a requeued job for about two minutes before starting it again. The test
    waits for the second run to log episodes past where the first one stopped, then cancels the job,
    so it does not depend on how many episodes this machine trains per minute."""
    sweep = tmp_path / "sweep"
    every = 100
    proc = _train(
        sweep,
        "seed=0",
        "algo.episodes=1000000",
        "env.reset_mode=air",
        f"checkpoint.every_episodes={every}",
        "logger.flush_every_s=1",
        "hydra.launcher.timeout_min=1",
        "hydra.launcher.signal_delay_s=10",
        "hydra.launcher.max_num_timeout=5",
        wait=False,
    )

    def logs() -> str:
        return "".join(p.read_text() for p in (sweep / ".submitit").rglob("*_log.*"))

    def rows_logged() -> int:
        csv = list(sweep.glob("*seed=0/episodes.csv"))
        return csv[0].read_text().count("\n") - 1 if csv else 0

    restart, deadline = None, time.time() + 420
    while time.time() < deadline and proc.poll() is None:
        restart = re.search(r"continuing from episode (\d+) .*?; (\d+) episode\(s\) logged after it", logs())
        if restart and rows_logged() > int(restart.group(1)) + int(restart.group(2)) + 1:
            break
        time.sleep(1)
    # submitit keeps each SLURM job's logs in a folder named by its job id.
    subprocess.run(["scancel", *(p.name for p in (sweep / ".submitit").iterdir() if p.is_dir())])
    output, _ = proc.communicate(timeout=300)
    text = logs()
    assert restart, (output or "")[-2000:] + text[-2000:]
    assert "Requeued job" in text, text[-2000:]
    start, repeated = int(restart.group(1)), int(restart.group(2))
    # It continued from a checkpoint and trained again at most one interval: a checkpoint flushes the
    # CSV before it writes last.pt, so a kill between the two leaves exactly one interval logged ...
    assert start > 0 and start % every == 0 and repeated <= every
    run = next(sweep.glob("*seed=0"))
    (rows, notes) = read_episodes(run / "episodes.csv")
    # ... and went on past where the first run stopped: nothing lost, nothing twice.
    episodes = rows["episode"].tolist()
    assert len(episodes) > start + repeated
    assert episodes == list(range(len(episodes)))
    assert not notes
    assert (run / "checkpoints" / "last.pt").is_file()
    print(f"restart from episode {start} ({repeated} trained again); {len(episodes)} episodes when cancelled")


def test_a_cancelled_job_is_reported_failed_and_a_rerun_finishes_it(tmp_path):
    sweep = tmp_path / "sweep"
    overrides = ("seed=0,1", "algo.episodes=2000", "env.reset_mode=air", "checkpoint.every_episodes=50")
    proc = _train(sweep, *overrides, wait=False)
    long_run = None
    deadline = time.time() + 120
    while time.time() < deadline:
        runs = list(sweep.glob("*seed=1"))
        if runs and (runs[0] / "checkpoints" / "last.pt").is_file():
            long_run = runs[0]
            break
        time.sleep(0.5)
    assert long_run is not None, "the long job never wrote a checkpoint"
    queue = subprocess.run(["squeue", "-h", "-o", "%i %j"], capture_output=True, text=True, check=True).stdout
    task = next(line.split()[0] for line in queue.splitlines() if line.split()[0].endswith("_1"))
    subprocess.run(["scancel", task], check=True)
    output, _ = proc.communicate(timeout=300)
    assert proc.returncode != 0
    assert "1 finished, 1 failed" in output, output[-3000:]
    assert "CANCELLED" in (long_run / "FAILED.txt").read_text()
    (other, _) = read_episodes(next(sweep.glob("*seed=0")) / "episodes.csv")
    assert other["episode"].tolist() == list(range(2000))  # the other job finished

    again = _train(sweep, *overrides)
    output = again.stdout + again.stderr
    assert again.returncode == 0, output[-3000:]
    assert "2 finished, 0 failed" in output
    (rows, _) = read_episodes(long_run / "episodes.csv")
    assert rows["episode"].tolist() == list(range(2000))
    assert not (long_run / "FAILED.txt").exists()


def test_a_large_sweep_runs_as_a_few_population_jobs(tmp_path):
    """hydra/launcher=slurm_population: 64 agents as 2 SLURM jobs of 32, each job folder as if it ran alone."""
    from hydra import compose, initialize_config_dir

    from drone_torchrl.config import config_dir
    from drone_torchrl.training.jobs import prepare
    from drone_torchrl.training.trainer import train_jobs

    sweep = tmp_path / "sweep"
    start = time.perf_counter()
    done = _train(
        sweep,
        "seed=range(0,64)",
        "algo.episodes=6",
        "hydra.launcher.agents_per_job=32",
        launcher="slurm_population",
    )
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-3000:]
    print(f"64 agents as 2 SLURM jobs: {time.perf_counter() - start:.1f} s")
    job = _job_id(output)
    assert _sacct(job, 2) == {f"{job}_0": "COMPLETED", f"{job}_1": "COMPLETED"}
    assert "64 finished, 0 failed" in output
    with initialize_config_dir(config_dir(), version_base="1.3"):
        for seed in (5, 40):  # one agent of each SLURM job, trained alone here
            cfg = compose("config", [*QUICK, "algo.episodes=6", f"seed={seed}"])
            (alone,) = train_jobs([prepare(cfg, tmp_path / f"alone{seed}")])
            (a, _) = read_episodes(alone.run_dir / "episodes.csv")
            (b, _) = read_episodes(next(sweep.glob(f"*seed={seed}")) / "episodes.csv")
            assert a["return"].tolist() == b["return"].tolist()
            assert a["length"].tolist() == b["length"].tolist()


def test_a_repeated_job_is_trained_once_under_slurm_population(tmp_path):
    """seed=0,1,2,0 with agents_per_job=2: the repeat of seed=0 goes into the SLURM job that trains
    seed=0 (not into the second one, which would train the same folder at the same time)."""
    sweep = tmp_path / "sweep"
    done = _train(
        sweep,
        "seed=0,1,2,0",
        "algo.episodes=4",
        "hydra.launcher.agents_per_job=2",
        launcher="slurm_population",
    )
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-3000:]
    job = _job_id(output)
    assert _sacct(job, 2) == {f"{job}_0": "COMPLETED", f"{job}_1": "COMPLETED"}
    assert "3 finished, 0 failed" in output, output[-3000:]
    (folder,) = sweep.glob("*seed=0")
    (episodes, notes) = read_episodes(folder / "episodes.csv")
    assert episodes["episode"].tolist() == [0, 1, 2, 3] and notes == []
    assert len((folder / "episodes.csv").read_text().splitlines()) == 1 + 4  # header + one row each
    logs = "".join(p.read_text() for p in sweep.rglob("*_log.out"))
    assert f"{folder}: job #3 is job #0 again (the same folder); trained once" in logs, logs[-3000:]
