"""Population runs (``hydra/launcher=population``): one folder for a group of agents.

- Each agent's episodes in the columnar record equal that job's ``episodes.csv`` when trained in
  its own folder (the same engine: only the bookkeeping differs); ``agents.parquet`` holds each
  agent's per-agent values; one stacked checkpoint.
- SIGTERM then resume, and a kill after a checkpoint then resume, equal one uninterrupted run:
  every agent's episodes exactly once, the same returns.
- A second process on the folder, and a population too big for memory, are refused in one line
  before anything is written.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from drone_torchrl import memory_estimate
from drone_torchrl.apps import train as train_app
from drone_torchrl.config import ConfigError, config_dir, validate
from drone_torchrl.io import run_lock
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes as read_csv
from drone_torchrl.training import population_record as record_module
from drone_torchrl.training.jobs import prepare
from drone_torchrl.training.signals import TrainingStopped
from drone_torchrl.training.trainer import train_jobs, train_population

pytest.importorskip("pyarrow")

COMMON = [
    "backend=fast",
    "env.max_steps=60",
    "eval.every_episodes=0",
    "eval.episodes=2",
    "eval.video=false",
    "progress=false",
    "checkpoint.every_episodes=4",
    "logger=csv",
    "logger.every_updates=1",
]
AGENTS = [("seed=0", "algo.lr=0.003"), ("seed=1", "algo.lr=0.003"), ("seed=0", "algo.lr=0.0003")]


def _cfgs(*overrides: str):
    cfgs = []
    with initialize_config_dir(config_dir(), version_base="1.3"):
        for agent in AGENTS:
            cfg = compose("config", overrides=[*COMMON, *overrides, *agent])
            validate(cfg)
            cfgs.append(cfg)
    return cfgs


NAMES = [" ".join(agent) for agent in AGENTS]


def _by_agent(run: Path) -> dict[int, list[tuple[int, float, int, str]]]:
    rows = record_module.read_episodes(run)
    out: dict[int, list] = {}
    for a, e, r, n, c in zip(
        rows["agent"], rows["episode"], rows["return"], rows["length"], rows["termination_cause"], strict=True
    ):
        out.setdefault(a, []).append((e, r, n, c))
    return out


def test_a_population_run_books_each_agent_as_its_own_run_would(tmp_path):
    """3 agents, 8 episodes each: the Parquet rows of agent k equal job k's episodes.csv (episode,
    return, length, cause) trained by the fused path in its own folder; agents.parquet names each
    agent's values; one checkpoint holds the stacked state ([3, ...]); the summaries are logged."""
    pop = tmp_path / "pop"
    outcomes = train_population(_cfgs("algo.episodes=8"), NAMES, pop)
    singles = train_jobs([prepare(cfg, tmp_path / str(k)) for k, cfg in enumerate(_cfgs("algo.episodes=8"))])
    rows = _by_agent(pop)
    assert sorted(rows) == [0, 1, 2]
    for k in range(3):
        cols, _ = read_csv(tmp_path / str(k) / "episodes.csv")
        assert [e for e, *_ in rows[k]] == cols["episode"].astype(int).tolist() == list(range(8))
        assert [r for _, r, _, _ in rows[k]] == pytest.approx(cols["return"].tolist(), rel=1e-6)
        assert [n for _, _, n, _ in rows[k]] == cols["length"].astype(int).tolist()
        assert [c for *_, c in rows[k]] == cols["termination_cause"].tolist()
        assert outcomes[k].final_return == pytest.approx(singles[k].final_return, rel=1e-6)
    agents = record_module.read_agents(pop)
    assert agents["agent"] == [0, 1, 2] and agents["name"] == NAMES
    assert agents["seed"] == [0, 1, 0] and agents["algo.lr"] == [0.003, 0.003, 0.0003]
    ckpt = load_checkpoint(pop / "checkpoints" / "last.pt")
    assert ckpt["kind"] == "population" and ckpt["state"]["params"].shape[0] == 3
    assert ckpt["episodes_done"] == [8, 8, 8] and all(f is not None for f in ckpt["final"])
    assert sorted(p.name for p in pop.iterdir()) == [
        ".lock",
        "agents.parquet",
        "checkpoints",
        "config.yaml",
        "csv",
        "episodes",
    ]
    scalars = (pop / "csv" / "scalars.csv").read_text()
    for tag in ("population/return_q50", "population/best_agent", "population/alive"):
        assert scalars.count(f",{tag},") == 8, tag  # one point per update (logger.every_updates=1)


def test_sigterm_then_resume_equals_one_uninterrupted_run(tmp_path, monkeypatch, capsys):
    """SIGTERM while update 6 is booked: the call in flight (updates 5..8: one call runs up to the
    checkpoint at 8) is finished, then stopped with a checkpoint at 8 episodes each (0..7 in the
    record); resumed to 12: every agent's episodes 0..11 exactly once, with the uninterrupted run's
    returns. Then a kill after the checkpoint at 8 (four episode parts written past it left on disk)
    and resumes to 10, then 12, give the same again: the parts past the checkpoint are removed."""
    whole, cut, killed = tmp_path / "whole", tmp_path / "cut", tmp_path / "killed"
    train_population(_cfgs("algo.episodes=12"), NAMES, whole)
    expected = _by_agent(whole)
    assert [e for e, *_ in expected[2]] == list(range(12))

    book = record_module.PopulationRecord.after_update

    def signal_at_six(self):
        book(self)
        if self.updates == 6:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(record_module.PopulationRecord, "after_update", signal_at_six)
    with pytest.raises(TrainingStopped) as stopped:
        train_population(_cfgs("algo.episodes=12"), NAMES, cut)
    monkeypatch.setattr(record_module.PopulationRecord, "after_update", book)
    assert stopped.value.run_dirs == [cut]
    from drone_torchrl.apps.train import _stopped

    with pytest.raises(SystemExit) as exited:  # drone-train's line: the sweep again, not resume=
        _stopped(stopped.value)
    assert exited.value.code == 128 + signal.SIGTERM
    assert "run the same command again" in capsys.readouterr().err
    assert load_checkpoint(cut / "checkpoints" / "last.pt")["episodes_done"] == [8, 8, 8]
    assert {k: [e for e, *_ in v] for k, v in _by_agent(cut).items()} == {k: list(range(8)) for k in range(3)}
    train_population(_cfgs("algo.episodes=12"), NAMES, cut)
    _same(_by_agent(cut), expected)

    flush = "logger.flush_every_s=0"  # a part per update: the killed run leaves 4 parts past episode 8
    train_population(_cfgs("algo.episodes=8", flush), NAMES, killed)
    at_eight = (killed / "checkpoints" / "last.pt").read_bytes()
    train_population(_cfgs("algo.episodes=12", flush), NAMES, killed)
    (killed / "checkpoints" / "last.pt").write_bytes(at_eight)  # killed before its checkpoint at 12
    train_population(_cfgs("algo.episodes=10", flush), NAMES, killed)  # writes 2 parts, not 4
    _same(_by_agent(killed), {k: rows[:10] for k, rows in expected.items()})
    train_population(_cfgs("algo.episodes=12", flush), NAMES, killed)
    _same(_by_agent(killed), expected)


def _same(got: dict, expected: dict) -> None:
    assert sorted(got) == sorted(expected)
    for k in expected:
        assert [(e, n, c) for e, _, n, c in got[k]] == [(e, n, c) for e, _, n, c in expected[k]], k
        assert [r for _, r, _, _ in got[k]] == pytest.approx([r for _, r, _, _ in expected[k]], rel=1e-6), k


HOLD = """
import sys, time
from drone_torchrl.io import run_lock
run_lock.hold(sys.argv[1])
print("held", flush=True)
time.sleep(60)
"""


def test_a_second_process_on_a_population_folder_is_refused(tmp_path):
    """Another process holds the folder: refused in one line naming its pid, nothing written."""
    pop = tmp_path / "pop"
    owner = subprocess.Popen([sys.executable, "-c", HOLD, str(pop)], stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout.readline().strip() == "held"
        with pytest.raises(run_lock.RunFolderBusy) as refused:
            train_population(_cfgs("algo.episodes=2"), NAMES, pop)
    finally:
        owner.kill()
        owner.wait()
    message = str(refused.value)
    assert "\n" not in message and f"pid {owner.pid}" in message and str(pop) in message
    assert sorted(p.name for p in pop.iterdir()) == [".lock"]


def test_a_population_too_big_for_memory_is_refused_with_the_estimate(tmp_path, monkeypatch):
    """Memory for 2 agents, a population of 3: refused in one line with the estimate, before the
    folder exists."""
    cfgs = _cfgs("algo.episodes=2")
    learner = memory_estimate.reinforce_parts
    two = memory_estimate.estimate(cfgs[0], 2, learner).total
    monkeypatch.setattr(memory_estimate, "available_ram", lambda: (two, "MemAvailable"))
    with pytest.raises(ConfigError, match=r"needs about .* of RAM available") as refused:
        train_population(cfgs, NAMES, tmp_path / "pop")
    assert "\n" not in str(refused.value)
    assert not (tmp_path / "pop").exists()


@pytest.mark.slow  # a real command (13 s)
def test_a_sweep_whose_population_is_refused_for_memory_exits_non_zero(tmp_path):
    """The same refusal through drone-train -m hydra/launcher=population: each job fits (the sweeper's
    check), the population of 3 does not. The population has no folder for the sweep's summary to
    count, so the command itself says so and exits non-zero (it said '0 failed' and exited 0), in one
    stderr line before the sweep folder exists (the reason was on stdout)."""
    two = memory_estimate.estimate(_cfgs("algo.episodes=2")[0], 2, memory_estimate.reinforce_parts).total
    sweep = tmp_path / "sweep"
    argv = ["drone-train", "-m", "hydra/launcher=population", "seed=0,1,2", "algo.episodes=2", *COMMON]
    argv.append(f"hydra.sweep.dir={sweep}")
    script = (
        "from drone_torchrl import memory_estimate\n"
        f"memory_estimate.available_ram = lambda: ({two}, 'MemAvailable')\n"
        "import sys\n"
        f"sys.argv = {argv!r}\n"
        "from drone_torchrl.apps.train import run\n"
        "run()\n"
    )
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, cwd=tmp_path, env=env
    )
    assert done.returncode != 0, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(
        "drone-train: error: 3 agents trained together in one population run: this config needs about"
    )
    assert "not started" not in done.stdout
    assert not sweep.exists()


def test_drone_eval_and_export_read_one_agent_back(tmp_path, monkeypatch):
    """drone-eval checkpoint=<population run> agent=K flies agent K alone (a standalone actor built
    from the stacked checkpoint): its mean return over the run's evaluation seeds equals what the
    trainer's evaluator measured for agent K inside the population (final eval_return). drone-export
    agent=K writes that agent's policy: its commands equal the actor's."""
    from drone_torchrl.comparison import run_eval
    from drone_torchrl.export import export_policy

    pop = tmp_path / "pop"
    # Bounded thrust: the agents' deterministic policies fly differently (60, 15, 34 here).
    outcomes = train_population(_cfgs("algo.episodes=8", "experiment=bounded"), NAMES, pop)
    evals = [o.final["eval_return"] for o in outcomes]
    assert len(set(evals)) == 3  # the agents differ, so reading the wrong one would show
    monkeypatch.chdir(tmp_path)
    for k in range(3):
        with initialize_config_dir(config_dir(), version_base="1.3"):
            cfg = compose(
                "eval",
                overrides=[f"checkpoint={pop}", f"agent={k}", "episodes=2", "video=false", "plot=false"],
            )
        results = run_eval(cfg)
        (flown,) = [r for name, r in results.items() if name.startswith("checkpoint")]
        assert flown["return_mean"] == pytest.approx(evals[k], rel=1e-5), k
    exported = export_policy(pop, tmp_path / "policy.pt2", agent=1)
    assert exported.path.is_file()


def test_a_diverged_agent_stops_alone_and_the_checkpoint_keeps_its_last_finite_state(tmp_path):
    """Agent 1's weights turn NaN right after the episode-4 checkpoint: it stops at the next update,
    the others finish; the population checkpoint keeps agent 1's episode-4 state (equal to that
    checkpoint's rows, all finite) and its failure; its episodes end at 3."""
    import torch

    from drone_torchrl.training.jobs import Job
    from drone_torchrl.training.trainer import Trainer

    pop = tmp_path / "pop"
    cfgs = _cfgs("algo.episodes=10", "checkpoint.every_episodes=2")
    trainer = Trainer([Job(cfg, pop) for cfg in cfgs], pop, NAMES)
    for _ in range(4):  # one episode per update: episodes 0..3, checkpoints after episodes 2 and 4
        trainer.step([0, 1, 2], 1)
    at_four = load_checkpoint(pop / "checkpoints" / "last.pt")
    with torch.no_grad():
        trainer.population.policy.params.get(("mean", "bias"))[1] = float("nan")
    finals = trainer.train()
    assert finals[0] is not None and finals[2] is not None and finals[1] is None
    last = load_checkpoint(pop / "checkpoints" / "last.pt")
    assert last["episodes_done"] == [10, 4, 10] and "non-finite actions" in last["failure"][1]
    for key, value in last["state"].items():
        torch.testing.assert_close(value[1], at_four["state"][key][1], rtol=0, atol=0)
    assert [e for e, *_ in _by_agent(pop)[1]] == [0, 1, 2, 3]


def test_resume_continues_one_agent_of_a_population_as_its_own_run(tmp_path):
    """resume=<population run> agent=1 continues agent 1 from the population's checkpoint (episode
    8) as a fork in a run folder of its own: its episodes 8..11 equal agent 1's in a population
    trained to 12 without a stop; the population's folder is left as it was."""
    from drone_torchrl.training.trainer import train

    pop, whole, fork = tmp_path / "pop", tmp_path / "whole", tmp_path / "fork"
    train_population(_cfgs("algo.episodes=8"), NAMES, pop)
    train_population(_cfgs("algo.episodes=12"), NAMES, whole)
    before = {p: p.read_bytes() for p in pop.rglob("*") if p.is_file() and p.name != ".lock"}
    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=[*COMMON, f"resume={pop}", "agent=1", "algo.episodes=12"])
    train(cfg, run_dir=fork)
    cols, _ = read_csv(fork / "episodes.csv")
    expected = _by_agent(whole)[1][8:]
    assert cols["episode"].astype(int).tolist() == [e for e, *_ in expected] == [8, 9, 10, 11]
    assert cols["return"].tolist() == pytest.approx([r for _, r, _, _ in expected], rel=1e-6)
    assert load_checkpoint(fork / "checkpoints" / "last.pt")["episodes_done"] == 12
    assert {p: p.read_bytes() for p in pop.rglob("*") if p.is_file() and p.name != ".lock"} == before


EXTEND = ["env.max_steps=20", "eval.episodes=1", "eval.video=false", "progress=false", "seed=0"]
SEARCHES = {
    "population": [],
    "pbt": ["hydra/launcher=pbt", "hydra.launcher.every_updates=2"],
    "halving": ["hydra/launcher=halving", "hydra.launcher.rungs=[2,4]"],
}


@pytest.mark.parametrize("search", list(SEARCHES))
def test_a_population_or_search_is_extended_by_raising_its_budget(tmp_path, command_here, search):
    """``drone-train -m hydra/launcher=<population|pbt|halving> ... algo.episodes=8``, then the same
    command with ``algo.episodes=16`` in its folder (``hydra.sweep.dir``): every agent continues to
    16 episodes, as a single run does with ``resume=<run> algo.episodes=16``. The episodes and a
    search's steps (the step due at update 8, skipped at the end of the first budget, included) are
    those of the command given 16 episodes from the start; agents.parquet names the new budget and
    ``.hydra/`` keeps how the run was started."""
    launcher = SEARCHES[search] or ["hydra/launcher=population"]
    command = ["-m", *launcher, "algo.lr=1e-4,3e-4,1e-3,3e-3", *EXTEND]

    def drone_train(budget: int, folder: str) -> Path:
        proc = command_here(
            train_app.run, "drone-train", *command, f"algo.episodes={budget}", f"hydra.sweep.dir={folder}",
            cwd=tmp_path,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr
        return tmp_path / folder / "population_0"

    extended = drone_train(8, "extended")
    record = (extended / ".hydra" / "overrides.yaml").read_bytes()
    assert load_checkpoint(extended / "checkpoints" / "last.pt")["episodes_done"] == [8] * 4
    assert drone_train(16, "extended") == extended
    state = load_checkpoint(extended / "checkpoints" / "last.pt")
    assert state["episodes_done"] == [16] * 4 and all(final is not None for final in state["final"])
    assert all(name.endswith("algo.episodes=16") for name in record_module.read_agents(extended)["name"])
    assert (extended / ".hydra" / "overrides.yaml").read_bytes() == record
    direct = drone_train(16, "direct")
    _same(_by_agent(extended), _by_agent(direct))
    assert all(len(rows) == 16 for rows in _by_agent(extended).values())
    if search != "population":
        lineage = record_module.read_table(extended / record_module.LINEAGE_TABLE)
        assert lineage == record_module.read_table(direct / record_module.LINEAGE_TABLE)
        if search == "pbt":
            assert lineage["update"] == [2, 4, 6, 8, 10, 12, 14]
