"""Sweeps under each Hydra launcher: every job gets its folder, re-running skips finished jobs, and a
failing job is reported while the others finish.

Each sweep is ``drone-train -m ...``: in this process for the launchers that train inside
drone-train's own process (basic, fused, population; ``IN_PROCESS``), as ``python -m
drone_torchrl.apps.train`` for those that start processes of their own. A launcher whose plugin is
not installed (extras ``joblib``, ``submitit``, ``ray``) is skipped. The Ray test starts a local Ray
instance and is skipped unless selected with ``-m ray``.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from drone_torchrl.apps import train as train_app
from drone_torchrl.config import config_dir
from drone_torchrl.training.jobs import FAILED_FILE, job_status, sweep_jobs

REPO = Path(__file__).resolve().parents[1]
TINY = ["algo.episodes=3", "env.max_steps=20", "eval.video=false", "eval.episodes=1"]
GRID = ["algo.lr=1e-3,1e-4", "seed=0,1"]  # 2 settings x 2 seeds
FAILING_GRID = ["algo.gamma=0.9,0.95"]  # the 0.95 job's folder is given a damaged checkpoint first
DAMAGED = "is not a readable checkpoint"


def _damage(sweep_dir: Path, *overrides: str, cwd: Path, here) -> None:
    """Run the gamma 0.95 job alone, then damage its checkpoint: re-running it fails at run time."""
    _multirun(sweep_dir, *overrides, "algo.gamma=0.95", cwd=cwd, here=here)
    (job,) = sweep_jobs(sweep_dir)
    (job / "checkpoints" / "last.pt").write_bytes(b"not a checkpoint")


# launcher id -> (plugin module to require or None, overrides that select it)
LAUNCHERS = {
    "basic": (None, []),
    "fused": (None, ["hydra/launcher=fused"]),
    "local_parallel": ("hydra_plugins.hydra_joblib_launcher", ["hydra/launcher=local_parallel"]),
    "local_submitit": ("hydra_plugins.hydra_submitit_launcher", ["hydra/launcher=local_submitit"]),
    "ray_local": ("hydra_plugins.hydra_ray_launcher", ["hydra/launcher=ray_local"]),
}


def _require(launcher: str, request: pytest.FixtureRequest) -> list[str]:
    module, overrides = LAUNCHERS[launcher]
    if launcher == "ray_local" and "ray" not in (request.config.option.markexpr or ""):
        pytest.skip("starts a local Ray instance; select with -m ray")
    if module is not None:
        pytest.importorskip(module)
    return overrides


# Launchers that train every job inside drone-train's own process: their sweeps run in this one
# (tests/conftest.py's command_here), as a new process would only add the imports of torch, TorchRL
# and Hydra. The others start processes of their own, so drone-train gets one too.
IN_PROCESS = {"basic", "fused", "population"}


def _multirun(sweep_dir: Path, *overrides: str, cwd: Path, here, expect_failure: bool = False) -> str:
    """Run a multirun to completion; returns its output plus any per-job logs submitit kept.

    A sweep with a failed job must exit non-zero (``expect_failure``), one without must exit 0.
    ``here``: the ``command_here`` fixture, which runs the IN_PROCESS launchers' sweeps."""
    launcher = next((o.split("=", 1)[1] for o in overrides if o.startswith("hydra/launcher=")), "basic")
    if launcher in IN_PROCESS:
        argv = ["-m", *overrides, *TINY, f"hydra.sweep.dir={sweep_dir}"]
        proc = here(train_app.run, "drone-train", *argv, cwd=cwd)
        out = proc.stdout + proc.stderr
        assert (proc.returncode != 0) == expect_failure, out
        assert "Traceback" not in proc.stderr, out
        return out
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy", "RAY_DEDUP_LOGS": "0"}
    # Hydra finds launcher plugins by listing hydra_plugins' folders; an editable install's import
    # hook is not one, so hydra/launcher=fused is only found with the checkout on the path.
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    cmd = [
        sys.executable,
        "-m",
        "drone_torchrl.apps.train",
        "-m",
        *overrides,
        *TINY,
        f"hydra.sweep.dir={sweep_dir}",
    ]
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    out = proc.stdout + proc.stderr
    assert (proc.returncode != 0) == expect_failure, out
    assert "Traceback" not in proc.stderr, out
    # submitit runs jobs in their own processes and keeps their stdout under .submitit/<job id>/.
    return out + "".join(p.read_text() for p in sorted(sweep_dir.glob(".submitit/*/*_log.*")))


def _snapshot(jobs: list[Path]) -> dict[Path, tuple[bytes, int]]:
    files = [job / name for job in jobs for name in ("episodes.csv", "checkpoints/last.pt")]
    return {f: (f.read_bytes(), f.stat().st_mtime_ns) for f in files}


@pytest.mark.parametrize(
    "launcher",
    [
        "basic",
        "fused",
        # ~20 s per sweep here: joblib and submitit start a process per job (torch, TorchRL and
        # Hydra imported in each), so they run with -m slow (.ci/run runs them as a stage).
        pytest.param("local_parallel", marks=pytest.mark.slow),
        pytest.param("local_submitit", marks=pytest.mark.slow),
        pytest.param("ray_local", marks=pytest.mark.ray),
    ],
)
def test_sweep_runs_then_skips_finished_jobs(launcher, request, tmp_path, command_here):
    overrides = _require(launcher, request)
    sweep_dir = tmp_path / "sweep"
    _multirun(sweep_dir, *overrides, *GRID, cwd=tmp_path, here=command_here)

    jobs = sweep_jobs(sweep_dir)
    assert len(jobs) == 4, jobs
    for job in jobs:
        with open(job / "episodes.csv", newline="") as f:
            assert len(list(csv.DictReader(f))) == 3, job
        assert job_status(job)[0] == "finished", (job, job_status(job))
    before = _snapshot(jobs)

    out = _multirun(sweep_dir, *overrides, *GRID, cwd=tmp_path, here=command_here)
    assert sweep_jobs(sweep_dir) == jobs
    for job in jobs:
        assert f"{job.name}: already finished" in out, out
    assert out.count("already finished") == 4, out
    assert _snapshot(jobs) == before  # nothing rewritten


@pytest.mark.parametrize(
    "launcher",
    [
        "basic",
        "fused",
        pytest.param("local_parallel", marks=pytest.mark.slow),  # a process per job: ~20 s
        pytest.param("ray_local", marks=pytest.mark.ray),
    ],
)
def test_failed_job_is_summarised_and_the_others_finish(launcher, request, tmp_path, command_here):
    overrides = _require(launcher, request)
    sweep_dir = tmp_path / "sweep"
    _damage(sweep_dir, *overrides, cwd=tmp_path, here=command_here)
    out = _multirun(
        sweep_dir, *overrides, *FAILING_GRID, cwd=tmp_path, here=command_here, expect_failure=True
    )

    jobs = {job.name.split(",")[0]: job for job in sweep_jobs(sweep_dir)}
    assert set(jobs) == {"algo.gamma=0.9", "algo.gamma=0.95"}, jobs
    assert job_status(jobs["algo.gamma=0.9"])[0] == "finished"
    status, reason = job_status(jobs["algo.gamma=0.95"])
    assert status == "failed" and DAMAGED in reason
    assert (jobs["algo.gamma=0.95"] / FAILED_FILE).is_file()
    assert "1 finished, 1 failed, 0 unfinished" in out, out
    failed_lines = [line for line in out.splitlines() if "[failed]" in line]
    assert len(failed_lines) == 1 and jobs["algo.gamma=0.95"].name in failed_lines[0], out
    assert DAMAGED in failed_lines[0]


@pytest.mark.parametrize("launcher", ["basic", "fused"])
def test_a_bad_value_in_a_sweep_is_refused_before_any_job(launcher, request, tmp_path, command_here):
    overrides = _require(launcher, request)
    sweep_dir = tmp_path / "sweep"
    out = _multirun(
        sweep_dir, *overrides, "algo.gamma=0.9,7", cwd=tmp_path, here=command_here, expect_failure=True
    )
    errors = [line for line in out.splitlines() if "error" in line]
    assert len(errors) == 1 and errors[0].startswith("drone-train: error: algo.gamma=7 is not allowed"), out
    assert sweep_jobs(sweep_dir) == [] and not list(sweep_dir.glob("*/episodes.csv"))


def _compose(*overrides: str):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


def test_launcher_presets_extend_the_plugins():
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    launcher = _compose("hydra/launcher=local_parallel", "hydra.launcher.n_jobs=8").hydra.launcher
    assert launcher._target_.endswith("JoblibLauncher") and launcher.n_jobs == 8
    assert launcher.prefer == "processes"
    launcher = _compose("hydra/launcher=local_submitit").hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.LocalLauncher")
    assert (launcher.timeout_min, launcher.cpus_per_task) == (1440, 1)


def test_slurm_preset_renders_an_sbatch_script(tmp_path, monkeypatch):
    """The slurm preset and its overrides reach sbatch (rendered by our launcher's executor, not submitted)."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    import submitit
    from omegaconf import OmegaConf

    from hydra_plugins.drone_torchrl_launcher.slurm_launcher import SlurmLauncher

    cfg = _compose("hydra/launcher=slurm", "hydra.launcher.partition=cpu", "hydra.launcher.mem_gb=2")
    params = OmegaConf.to_container(cfg.hydra.launcher, resolve=False)
    assert params.pop("_target_") == "hydra_plugins.drone_torchrl_launcher.slurm_launcher.SlurmLauncher"
    assert (params["cpus_per_task"], params["tasks_per_node"], params["timeout_min"]) == (1, 1, 240)
    monkeypatch.setattr(submitit.SlurmExecutor, "affinity", staticmethod(lambda: 1))  # no srun here
    executor = SlurmLauncher(**{**params, "submitit_folder": str(tmp_path)})._executor()
    executor.update_parameters(name="drone-train")
    sbatch = executor._executor._make_submission_file_text("python -u -m submitit.core._submit", "uid")
    for line in (
        "#SBATCH --partition=cpu",
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --ntasks-per-node=1",
        "#SBATCH --time=240",
        "#SBATCH --mem=2GB",
    ):
        assert line in sbatch, sbatch


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_parallel_env_starts_inside_a_joblib_worker(tmp_path):
    """``env.num_workers>0`` under the joblib launcher: its workers' global start method is "loky",
    which a spawned ParallelEnv worker cannot re-apply unless make_env resets it to "spawn"."""
    pytest.importorskip("joblib")
    script = (
        "import multiprocessing as mp\n"
        "import joblib.externals.loky.backend.context  # registers 'loky', as in a joblib worker\n"
        "mp.set_start_method('loky', force=True)\n"
        "from drone_torchrl.envs.factory import make_env\n"
        "env = make_env(num_envs=2, num_workers=1)\n"
        "env.set_seed(0)\n"
        "print('batch', tuple(env.rollout(3).batch_size)[:2])\n"
        "env.close()\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "batch (1, 2)" in proc.stdout, proc.stdout


def test_a_failed_job_does_not_stop_later_batches(tmp_path, command_here):
    """The failing job first, one job per batch: Hydra's basic sweeper used to stop after it."""
    sweep_dir = tmp_path / "sweep"
    _damage(sweep_dir, "hydra/launcher=fused", cwd=tmp_path, here=command_here)
    out = _multirun(
        sweep_dir,
        "hydra/launcher=fused",
        "algo.gamma=0.95,0.9",
        "hydra.sweeper.max_batch_size=1",
        cwd=tmp_path,
        here=command_here,
        expect_failure=True,
    )
    jobs = {job.name.split(",")[0]: job for job in sweep_jobs(sweep_dir)}
    assert job_status(jobs["algo.gamma=0.9"])[0] == "finished"
    assert job_status(jobs["algo.gamma=0.95"])[0] == "failed"
    assert "1 finished, 1 failed, 0 unfinished" in out, out
    assert out.count(DAMAGED) <= 3, out  # the job's line, the summary, FAILED.txt's


def test_a_repeated_job_trains_once_and_reports_its_outcome(tmp_path, command_here):
    """seed=0,0 under the fused launcher: one folder, one agent trained, both jobs report it (the basic
    launcher would train the first and find the second already finished)."""
    sweep_dir = tmp_path / "sweep"
    out = _multirun(sweep_dir, "hydra/launcher=fused", "algo.gamma=0.9,0.9", cwd=tmp_path, here=command_here)
    (job,) = sweep_jobs(sweep_dir)
    assert job_status(job)[0] == "finished"
    assert f"{job}: job #1 is job #0 again (the same folder); trained once" in out, out
    assert "1 finished, 0 failed, 0 unfinished" in out, out
    assert out.count(": 3 episodes, running-mean") == 1, out  # trained (and reported) once


def test_slurm_population_keeps_the_jobs_of_one_folder_in_one_slurm_job():
    """Two SLURM jobs must never train one folder at once: a job that repeats an earlier one's folder
    goes into that job's SLURM job (whose fused launcher trains it once); ``agents_per_job`` counts
    distinct folders."""
    from hydra_plugins.drone_torchrl_launcher.slurm_launcher import population_groups

    folders = ["a", "b", "a", "c", "d", "b", "e"]
    assert population_groups(folders, 2) == [[0, 1, 2, 5], [3, 4], [6]]
    assert population_groups(folders, 32) == [[0, 1, 2, 3, 4, 5, 6]]
    assert population_groups(["a", "a", "a"], 1) == [[0, 1, 2]]
    assert population_groups(list("abc"), 1) == [[0], [1], [2]]
    assert population_groups([], 4) == []


def test_slurm_population_refuses_a_bad_agents_per_job():
    """A bad hydra.launcher.agents_per_job stops the sweep with one line, before any job is submitted."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from omegaconf import OmegaConf

    from hydra_plugins.drone_torchrl_launcher.slurm_launcher import SlurmPopulationLauncher

    for bad in ("0", "-3", "abc", "2.5", "true"):
        cfg = _compose("hydra/launcher=slurm_population", f"hydra.launcher.agents_per_job={bad}")
        params = OmegaConf.to_container(cfg.hydra.launcher, resolve=False)
        del params["_target_"]
        shown = {"true": "True"}.get(bad, bad)
        with pytest.raises(
            SystemExit,
            match=rf"^drone-train: error: hydra.launcher.agents_per_job={shown} is not allowed; "
            r"expected an integer >= 1$",
        ):
            SlurmPopulationLauncher(**params)
    cfg = _compose("hydra/launcher=slurm_population")
    params = OmegaConf.to_container(cfg.hydra.launcher, resolve=False)
    del params["_target_"]
    assert SlurmPopulationLauncher(**params).params["agents_per_job"] == 32


def test_population_launcher_trains_each_group_in_one_folder(tmp_path, command_here):
    """hydra/launcher=population: 2 lr x 2 seeds x 2 evaluation seeds = 8 jobs; eval.seed is not a
    per-agent key, so two population runs of 4 agents each, each one folder with one ``.hydra/``,
    agents.parquet, the episodes' parts and one checkpoint; re-running finds both finished."""
    pytest.importorskip("pyarrow")
    from drone_torchrl.training.population_record import read_agents, read_episodes

    sweep_dir = tmp_path / "sweep"
    grid = [*GRID, "eval.seed=5,10"]
    out = _multirun(sweep_dir, "hydra/launcher=population", *grid, cwd=tmp_path, here=command_here)
    folders = sorted(p for p in sweep_dir.iterdir() if p.is_dir())
    assert [p.name for p in folders] == ["population_0", "population_1"], out
    assert sweep_jobs(sweep_dir) == folders
    for folder in folders:
        agents = read_agents(folder)
        assert sorted(zip(agents["algo.lr"], agents["seed"], strict=True)) == [
            (1e-4, 0),
            (1e-4, 1),
            (1e-3, 0),
            (1e-3, 1),
        ]
        rows = read_episodes(folder)
        assert sorted(zip(rows["agent"], rows["episode"], strict=True)) == [
            (a, e) for a in range(4) for e in range(3)
        ]
        assert job_status(folder) == ("finished", "population of 4 agents: 4 finished, 0 failed")
        assert not list(folder.glob("**/episodes.csv"))
    again = _multirun(sweep_dir, "hydra/launcher=population", *grid, cwd=tmp_path, here=command_here)
    assert again.count("already finished (4 agents); nothing to do") == 2, again
    # drone-report reads each agent as the run it would be in its own folder: 2 settings (algo.lr)
    # of 4 runs (eval.seed, which picks the evaluation's starts, is not a setting).
    from drone_torchrl.apps.report import main as report_main
    from drone_torchrl.report.runs import group_runs, load_runs

    runs = load_runs(sweep_dir)
    assert len(runs) == 8 and all(run.episodes == 3 and run.status == "finished" for run in runs)
    assert sorted(len(setting.runs) for setting in group_runs(runs)) == [4, 4]
    report_main([str(sweep_dir), "--no-pd", "--out", str(tmp_path / "report")])
    assert (tmp_path / "report").is_dir() and any((tmp_path / "report").iterdir())


def test_population_runs_are_numbered_on_across_the_sweeper_s_batches(tmp_path, command_here):
    """hydra.sweeper.max_batch_size=2 hands the population launcher two batches: each is a population
    run of its own, population_0 and population_1 (the second batch used to find population_0 holding
    the first batch's agents, and was refused)."""
    pytest.importorskip("pyarrow")
    from drone_torchrl.training.population_record import read_agents

    sweep_dir = tmp_path / "sweep"
    grid = ["hydra/launcher=population", *GRID, "hydra.sweeper.max_batch_size=2"]
    _multirun(sweep_dir, *grid, cwd=tmp_path, here=command_here)
    assert [p.name for p in sweep_jobs(sweep_dir)] == ["population_0", "population_1"]
    assert [read_agents(sweep_dir / f"population_{g}")["seed"] for g in (0, 1)] == [[0, 1], [0, 1]]


def test_a_sweep_of_per_agent_values_is_one_config_and_trains_as_each_jobs_own_config(tmp_path, command_here):
    """seed=0,1 x algo.lr=1e-3,1e-4 differ only in per-agent numbers: the launcher reads them from the
    overrides' text into one config and a column per key (no config per job), and the population
    equals the one trained from each job's own composed config: the same values per agent and the
    same episodes (a value read as another number, or given to another agent, differs)."""
    pytest.importorskip("pyarrow")
    from hydra import compose, initialize_config_dir

    from drone_torchrl.config import validate
    from drone_torchrl.training.population_record import read_agents, read_episodes
    from drone_torchrl.training.trainer import train_population

    sweep_dir = tmp_path / "sweep"
    out = _multirun(sweep_dir, "hydra/launcher=population", *GRID, cwd=tmp_path, here=command_here)
    assert "4 jobs differ only in per-agent values: one population from one config" in out, out
    jobs = [
        ["algo.lr=1e-3", "seed=0"],
        ["algo.lr=1e-3", "seed=1"],
        ["algo.lr=1e-4", "seed=0"],
        ["algo.lr=1e-4", "seed=1"],
    ]
    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfgs = [compose("config", overrides=[*job, *TINY]) for job in jobs]
    for cfg in cfgs:
        validate(cfg)
    alone = tmp_path / "alone"
    train_population(cfgs, [" ".join(job) for job in jobs], alone)
    swept = sweep_dir / "population_0"
    written = yaml.safe_load((swept / ".hydra" / "overrides.yaml").read_text())
    assert [job[:2] for job in written] == [
        ["algo.lr=0.001", "seed=0"],
        ["algo.lr=0.001", "seed=1"],
        ["algo.lr=0.0001", "seed=0"],
        ["algo.lr=0.0001", "seed=1"],
    ]
    (agents, expected_agents) = (read_agents(swept), read_agents(alone))
    del agents["name"], expected_agents["name"]  # Hydra writes the sweep's values as 0.001
    assert agents == expected_agents and [type(seed) for seed in agents["seed"]] == [int] * 4
    assert read_agents(swept)["algo.lr"] == [1e-3, 1e-3, 1e-4, 1e-4]
    rows, expected = read_episodes(swept), read_episodes(alone)
    for key in ("agent", "episode", "return", "length", "termination_cause"):
        assert rows[key] == expected[key], key


def test_drone_train_registers_every_launcher_and_sweeper_of_the_package(monkeypatch):
    """Hydra finds plug-ins by listing hydra_plugins' folders, which an editable install does not have
    (``hydra/launcher=population`` was an "Unknown plugin class" traceback run outside the checkout):
    drone-train registers each Launcher and Sweeper class our package defines. Hydra's registry is
    emptied of them first, so only the registration can put them back."""
    import importlib
    import inspect
    import pkgutil

    from hydra.core.plugins import Plugins
    from hydra.plugins.launcher import Launcher
    from hydra.plugins.sweeper import Sweeper

    import hydra_plugins.drone_torchrl_launcher as package
    from drone_torchrl.apps.train import register_plugins

    ours = set()
    for info in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
        module = importlib.import_module(info.name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            # (a private class is no plug-in a config can name)
            if (
                cls.__module__ == module.__name__
                and issubclass(cls, (Launcher, Sweeper))
                and cls.__name__[0] != "_"
            ):
                ours.add(f"{cls.__module__}.{cls.__name__}")
    # One launcher for fused, population and every search (conf/hydra/launcher/*.yaml preset it).
    assert {name.rsplit(".", 1)[1] for name in ours} >= {"PopulationLauncher", "PopulationSweeper"}
    registry = Plugins.instance().class_name_to_class
    monkeypatch.setattr(
        Plugins.instance(), "class_name_to_class", {k: v for k, v in registry.items() if k not in ours}
    )
    register_plugins()
    assert ours <= set(Plugins.instance().class_name_to_class)
