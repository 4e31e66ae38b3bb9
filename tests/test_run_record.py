"""One loop, one run record: regressions found in the two backends' code, and the checkpoint format."""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

import drone_torchrl
from drone_torchrl.config import ConfigError, config_dir
from drone_torchrl.io.checkpoint import (
    DIGEST_KEY,
    FORMAT_VERSION,
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
)
from drone_torchrl.io.episodes_csv import read_episodes
from drone_torchrl.modules import make_actor
from drone_torchrl.objectives import ReinforceLoss
from drone_torchrl.training.jobs import job_status, prepare
from drone_torchrl.training.trainer import Trainer, train, train_jobs

BACKENDS = ["reference", "fast"]
FAST = ["progress=false", "eval.episodes=2", "eval.video=false", "env.max_steps=30"]


def _cfg(*overrides: str, name: str = "config"):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose(name, overrides=list(overrides))


def _snapshot(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*")) if p.is_file()}


def _tb_steps(run: Path, tag: str) -> list[int]:
    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    return [e.step for e in events.Scalars(tag)] if tag in events.Tags()["scalars"] else []


@pytest.mark.parametrize("backend", BACKENDS)
def test_resume_from_best_forks_and_leaves_the_run_alone(tmp_path, backend, capsys):
    """resume=<run>/checkpoints/best.pt used to continue from last.pt (fused engine) or in the parent's
    folder. best.pt here is the episode-2 checkpoint: at lr 1e-9 every evaluation scores the same, and
    best.pt is only replaced by a strictly better one."""
    run, fork = tmp_path / "run", tmp_path / "fork"
    common = [
        f"backend={backend}",
        "algo.lr=1e-9",
        "eval.every_episodes=2",
        "checkpoint.every_episodes=2",
        *FAST,
    ]
    train(_cfg("algo.episodes=8", *common), run_dir=run)
    best = run / "checkpoints" / "best.pt"
    assert load_checkpoint(best)["episodes_done"] == 2
    before = _snapshot(run)

    train(_cfg(f"resume={best}", "algo.episodes=6", "progress=false"), run_dir=fork)
    assert "continuing as a fork in" in capsys.readouterr().out
    assert _snapshot(run) == before  # the parent's CSV, TensorBoard and checkpoints are untouched
    parent, _ = read_episodes(run / "episodes.csv")
    child, _ = read_episodes(fork / "episodes.csv")
    assert child["episode"].tolist() == list(range(6))
    # Same weights, optimizer and RNG streams as the parent at episode 2: the fork replays it.
    np.testing.assert_array_equal(child["return"], parent["return"][:6])
    np.testing.assert_array_equal(child["length"], parent["length"][:6])
    last = load_checkpoint(fork / "checkpoints" / "last.pt")
    assert last["episodes_done"] == 6 and last["final"] is not None
    assert _tb_steps(fork, "eval/return") == [4, 6]


def _tb_points(run: Path, tag: str) -> dict[int, float]:
    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    points = [(e.step, e.value) for e in events.Scalars(tag)]
    assert len({step for step, _ in points}) == len(points), points  # each step once
    return dict(points)


def _whole_and_killed_then_resumed(tmp_path: Path, *overrides: str) -> tuple[Path, Path]:
    """Two runs of 8 episodes (checkpoints and evaluations every 4, logs every update): ``whole``
    uninterrupted; ``cut`` trained to 4, on to 6, put back to its checkpoint at 4 (as if killed
    after logging episodes 5-6), then resumed to 8."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    common = [
        "logger.every_updates=1",
        "checkpoint.every_episodes=4",
        "eval.every_episodes=4",
        *FAST,
        *overrides,
    ]
    train(_cfg("algo.episodes=8", *common), run_dir=whole)
    train(_cfg("algo.episodes=4", *common), run_dir=cut)
    at_four = (cut / "checkpoints" / "last.pt").read_bytes()
    train(_cfg(f"resume={cut}", "algo.episodes=6", "progress=false"))
    (cut / "checkpoints" / "last.pt").write_bytes(at_four)  # as if killed before the next checkpoint
    train(_cfg(f"resume={cut}", "algo.episodes=8", "progress=false"))
    return whole, cut


def test_resume_keeps_the_checkpoints_own_tensorboard_points(tmp_path):
    """Killed after logging episodes 5-6 past its checkpoint at 4, then resumed to 8: TensorBoard has
    every step 1..8 once, the checkpoint's own last update and evaluation (step 4) included, and the
    values after it are the resumed run's (as in one uninterrupted run)."""
    whole, cut = _whole_and_killed_then_resumed(tmp_path)
    for tag in ("train/running_mean_return", "episode/return", "eval/return"):
        expected = _tb_points(whole, tag)
        assert sorted(expected) == ([4, 8] if tag == "eval/return" else list(range(1, 9)))
        assert _tb_points(cut, tag) == pytest.approx(expected, rel=1e-6), tag


def _csv_points(run: Path, tag: str) -> dict[int, float]:
    import csv

    with (run / "csv" / "scalars.csv").open(newline="") as f:
        points = [(int(r["step"]), float(r["value"])) for r in csv.DictReader(f) if r["tag"] == tag]
    assert len({step for step, _ in points}) == len(points), points  # each step once
    return dict(points)


def test_csv_logger_resumes_as_one_uninterrupted_run(tmp_path):
    """logger=csv: the same kill-and-resume as above; scalars.csv then holds every step once, as the
    uninterrupted run's does, and hparams.csv the final metrics."""
    whole, cut = _whole_and_killed_then_resumed(tmp_path, "logger=csv")
    for tag in ("train/running_mean_return", "episode/return", "eval/return"):
        expected = _csv_points(whole, tag)
        assert sorted(expected) == ([4, 8] if tag == "eval/return" else list(range(1, 9)))
        assert _csv_points(cut, tag) == pytest.approx(expected, rel=1e-6), tag
    assert not (cut / "tensorboard").exists()
    hparams = (cut / "csv" / "hparams.csv").read_text().splitlines()
    assert hparams[0] == "key,value" and any(line.startswith("hparam/final_return,") for line in hparams)


def test_csv_logger_writes_long_rows_and_its_float_format(tmp_path):
    from drone_torchrl.loggers.csvfile import CSVLogger

    full, short = CSVLogger(tmp_path / "full"), CSVLogger(tmp_path / "short", float_format="%.3g")
    for logger in (full, short):
        logger.log_scalars([("a", 0.123456789, 1), ("b", 2.0, 1)])
        logger.log_metrics({"a": 1 / 3}, step=2)
        logger.close()
    assert (tmp_path / "full" / "scalars.csv").read_text().splitlines() == [
        "step,tag,value",
        "1,a,0.123456789",
        "1,b,2.0",
        f"2,a,{1 / 3!r}",
    ]
    assert (tmp_path / "short" / "scalars.csv").read_text().splitlines()[1:] == [
        "1,a,0.123",
        "1,b,2",
        "2,a,0.333",
    ]


def test_mlflow_logger_keeps_one_run_across_a_resume(tmp_path):
    """logger=mlflow: the kill-and-resume above; read back through MlflowClient, the MLflow run has
    every step once with the uninterrupted run's values (REINFORCE retrains the skipped steps
    exactly), the config as params, the final metrics, and status FINISHED."""
    pytest.importorskip("mlflow")
    from mlflow.tracking import MlflowClient

    whole, cut = _whole_and_killed_then_resumed(tmp_path, "logger=mlflow")
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    (experiment,) = [e for e in client.search_experiments() if e.name == "adhoc"]
    runs = {r.data.tags["run_dir"]: r for r in client.search_runs([experiment.experiment_id])}
    assert sorted(runs) == sorted([str(whole), str(cut)])  # one MLflow run each, resumes included
    for tag in ("train/running_mean_return", "episode/return", "eval/return"):
        got = {}
        for run_dir, run in runs.items():
            history = [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, tag)]
            assert len({step for step, _ in history}) == len(history), (tag, history)  # each step once
            got[run_dir] = dict(history)
        assert sorted(got[str(whole)]) == ([4, 8] if tag == "eval/return" else list(range(1, 9)))
        if tag == "eval/return":  # append-only: the interrupted process's final evaluation (at 6) stays
            assert sorted(got[str(cut)]) == [4, 6, 8]
            del got[str(cut)][6]
        assert got[str(cut)] == pytest.approx(got[str(whole)], rel=1e-6), tag
    run = client.get_run(runs[str(cut)].info.run_id)
    assert run.info.status == "FINISHED" and run.data.params["algo.lr"] == "0.0001"
    assert "hparam/final_return" in run.data.metrics


def test_a_continued_run_keeps_its_logger_backend(tmp_path):
    run = tmp_path / "run"
    train(_cfg("algo.episodes=2", *FAST), run_dir=run)
    with pytest.raises(ConfigError, match=r"logger.backend 'tensorboard' -> 'csv'") as error:
        prepare(
            _cfg(f"resume={run}", "algo.episodes=4", "logger=csv"),
            requested=["logger=csv", "algo.episodes=4"],
        )
    assert "\n" not in str(error.value)


# A name no plug-in can have (the registries take lowercase identifiers only): unknown for good.
UNREGISTRABLE = "no such-backend"


def test_the_logger_backends_are_registered():
    from drone_torchrl import loggers
    from drone_torchrl.config import options_by_plugin

    names = loggers.BACKENDS.names()
    assert "tensorboard" in names and list(names) == sorted(names)
    assert sorted(options_by_plugin("logger")) == list(names)  # each has its conf/logger option
    with pytest.raises(
        ConfigError, match=rf"^logger.backend='{UNREGISTRABLE}' is not allowed; expected one of "
    ):
        loggers.get(UNREGISTRABLE)
    with pytest.raises(ValueError, match="cannot be registered"):
        loggers.register(loggers.Backend(UNREGISTRABLE, make=None, resume_rule=""))
    assert str(list(names)) in str(pytest.raises(ConfigError, loggers.get, UNREGISTRABLE).value)


def test_fork_needs_a_folder_of_its_own(tmp_path):
    run = tmp_path / "run"
    train(_cfg("algo.episodes=2", "eval.every_episodes=2", *FAST), run_dir=run)
    with pytest.raises(ConfigError, match="fork"):
        prepare(_cfg(f"resume={run / 'checkpoints' / 'best.pt'}"), run_dir=run)


@pytest.mark.parametrize("backend", BACKENDS)
def test_final_evaluation_is_not_repeated(tmp_path, backend):
    """algo.episodes a multiple of eval.every_episodes: one evaluation per point, one video each."""
    run = tmp_path / "run"
    train(
        _cfg(f"backend={backend}", "algo.episodes=4", "eval.every_episodes=2", *FAST, "eval.video=true"),
        run_dir=run,
    )
    assert sorted(p.name for p in (run / "videos").iterdir()) == ["episode_000002.mp4", "episode_000004.mp4"]
    assert _tb_steps(run, "eval/return") == [2, 4]


def test_reference_backend_with_worker_processes(tmp_path):
    """env.num_workers=1 with 2 episodes per update used to crash inside TorchRL after the folder was written."""
    run = tmp_path / "run"
    cfg = _cfg(
        "backend=reference", "env.num_workers=1", "algo.episodes_per_update=2", "algo.episodes=4", *FAST
    )
    train(cfg, run_dir=run)
    rows, _ = read_episodes(run / "episodes.csv")
    assert rows["episode"].tolist() == [0, 1, 2, 3]
    assert rows["update"].tolist() == [1, 1, 2, 2]
    assert all(1 <= n <= 30 for n in rows["length"])


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["env.num_workers=2", "algo.episodes_per_update=3"],
            "env.num_workers=2 is not allowed; expected a divisor",
        ),
        (
            ["backend=fast", "env.num_workers=1"],
            "env.num_workers=1 is not allowed; expected 0 with backend=fast",
        ),
    ],
)
def test_worker_settings_refused_before_any_work(tmp_path, overrides, message):
    cfg = _cfg("backend=reference", *overrides, *FAST)
    with pytest.raises(ConfigError, match=message):
        train(cfg, run_dir=tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("preset", ["paper", "bounded"])
def test_population_loss_equals_the_torchrl_actor_loss(tmp_path, preset):
    """On one stored rollout (sampled by the TorchRL env + actor), the loop's loss over the stacked
    population actor equals ReinforceLoss over a plain make_actor() with the same weights: same
    loss, same gradient. (The fast engine's loss and gradient: tests/test_kernels.py.)"""
    common = [
        "backend=reference",
        f"experiment={preset}",
        "algo.episodes_per_update=3",
        "algo.baseline=mean",
        *FAST,
    ]
    cfg = _cfg(*common)
    trainer = Trainer([prepare(cfg, tmp_path / "run")])
    batch = trainer.learner.collector.collect(torch.ones(1, dtype=torch.bool))  # [1, 3, T]
    assert batch.shape[:2] == (1, 3)
    update, policy = trainer.learner, trainer.population.policy
    loss = update.loss(batch.clone())  # ReinforceLoss through the population's actor
    policy.flat.grad = None
    loss["loss_reinforce"].backward()
    grads = policy.views(policy.flat.grad)

    actor = make_actor(
        cfg.model.distribution,
        list(cfg.model.hidden_sizes),
        cfg.model.activation,
        cfg.model.min_std,
        cfg.env.max_thrust,
    )
    actor.module[0].module.load_state_dict(policy.agent_state_dict(0))
    plain = ReinforceLoss(actor, gamma=cfg.algo.gamma, baseline="mean")(batch[0].clone())
    plain["loss_reinforce"].backward()

    assert float(plain["loss_reinforce"].detach()) != 0.0
    torch.testing.assert_close(
        loss["loss_reinforce"].detach(), plain["loss_reinforce"].detach(), rtol=1e-5, atol=1e-6
    )
    for name, param in actor.module[0].module.named_parameters():
        stacked_grad = grads.get(tuple(name.split(".")))[0]
        assert param.grad.abs().sum() > 0
        torch.testing.assert_close(stacked_grad, param.grad, rtol=1e-4, atol=1e-6)
    trainer.close()


# ----------------------------------------------------------------------------------- checkpoints


class _Payload:
    """Unpickling this runs ``open(<marker>, "w")``: what a crafted checkpoint could do."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.mark.parametrize("backend", BACKENDS)
def test_checkpoints_are_tensors_and_plain_data(tmp_path, backend):
    run = tmp_path / "run"
    train(_cfg(f"backend={backend}", "algo.episodes=2", *FAST), run_dir=run)
    state = torch.load(run / "checkpoints" / "last.pt", weights_only=True)
    assert state["format_version"] == FORMAT_VERSION == 4
    assert isinstance(state["config"], dict) and state["config"]["seed"] == 0
    assert all(v is None or isinstance(v, torch.Tensor) for v in state["rng"].values())
    # The TorchRL collector samples from torch's RNG and the env's generator; the fast path's
    # counter-based noise needs no state beyond the update count.
    has_state = {k: v is not None for k, v in state["rng"].items()}
    assert has_state == {"torch": backend == "reference", "env": backend == "reference", "agent": False}


def test_a_crafted_checkpoint_runs_no_code(tmp_path):
    run = tmp_path / "run"
    train(_cfg("algo.episodes=2", *FAST), run_dir=run)
    last = run / "checkpoints" / "last.pt"
    state = torch.load(last, weights_only=True)
    marker = tmp_path / "pwned"
    torch.save({**state, "final": _Payload(marker)}, last)

    with pytest.raises(CheckpointError, match=rf"^{last}.*refusing to unpickle"):
        load_checkpoint(last)
    with pytest.raises(ConfigError, match=str(last)):
        prepare(_cfg(f"resume={run}"))
    from drone_torchrl.comparison import run_eval

    with pytest.raises(ConfigError, match=str(last)):
        run_eval(_cfg(f"checkpoint={run}", "episodes=1", "video=false", "plot=false", name="eval"))
    status, detail = job_status(run)
    assert status == "unfinished" and "refusing to unpickle" in detail
    assert not marker.exists()


def test_version_1_checkpoints_are_migrated_and_resume(tmp_path):
    """A checkpoint written before format_version existed (RNG states under *_rng, no final key)."""
    common = ["backend=reference", "checkpoint.every_episodes=2", "eval.every_episodes=0", *FAST]
    whole, old = tmp_path / "whole", tmp_path / "old"
    train(_cfg("algo.episodes=4", *common), run_dir=whole)
    train(_cfg("algo.episodes=4", *common), run_dir=old)
    # Rewrite old's episode-2 state in the version-1 layout, as if the run had stopped there.
    shutil.rmtree(old)
    train(_cfg("algo.episodes=2", *common), run_dir=old)
    last = old / "checkpoints" / "last.pt"
    state = torch.load(last, weights_only=True)
    rng = state.pop("rng")
    state.pop("format_version")
    state.pop("final")
    state.pop("backend")  # version 1 had no engine key either (the reference's loop was the only one)
    state.pop(DIGEST_KEY)  # written since; a version-1 file has none
    state.update(torch_rng=rng["torch"], env_rng=rng["env"], agent_rng=rng["agent"])
    torch.save(state, last)

    migrated = load_checkpoint(last)
    assert migrated["format_version"] == FORMAT_VERSION and migrated["final"] is None
    assert torch.equal(migrated["rng"]["torch"], rng["torch"]) and torch.equal(
        migrated["rng"]["env"], rng["env"]
    )
    train(_cfg(f"resume={old}", "algo.episodes=4", "progress=false"))
    a, _ = read_episodes(whole / "episodes.csv")
    b, _ = read_episodes(old / "episodes.csv")
    np.testing.assert_array_equal(a["return"], b["return"])


def test_unknown_checkpoint_versions_are_refused_in_one_line(tmp_path):
    path = tmp_path / "future.pt"
    save_checkpoint({"format_version": 99, "actor": {}, "config": {}}, path)
    with pytest.raises(CheckpointError, match=rf"^{path} has format_version=99; .* reads 1 to 4$"):
        load_checkpoint(path)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=rf"^{garbage} is not a readable checkpoint"):
        load_checkpoint(garbage)


# ----------------------------------------------------------------------------------- layout


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """Every import (module level or inside functions) between our own modules."""
    root = Path(drone_torchrl.__file__).resolve().parents[1]
    files = [*root.joinpath("drone_torchrl").rglob("*.py"), *root.joinpath("hydra_plugins").rglob("*.py")]
    modules = {_module_name(f, root): f for f in files if "conf" not in f.parts}
    ours = ("drone_torchrl", "hydra_plugins")
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                # "from pkg import sub" imports pkg.sub when that is a module, else pkg itself.
                targets = [
                    f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in modules else node.module
                    for a in node.names
                ]
            else:
                continue
            graph[name] |= {t for t in targets if t.startswith(ours) and t in modules and t != name}
    return graph


def test_no_import_cycles():
    graph = _import_graph()
    assert "drone_torchrl.training.trainer" in graph and len(graph) > 20
    state: dict[str, int] = {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt) :] + [nxt] if nxt in stack else [node, nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, [*stack, nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


def test_apps_are_imported_by_nothing():
    graph = _import_graph()
    apps = {m for m in graph if m.startswith("drone_torchrl.apps.")}
    assert {"drone_torchrl.apps.train", "drone_torchrl.apps.evaluate", "drone_torchrl.apps.report"} <= apps
    # The apps share their --help page and console entry points (apps.help, apps.commands) among themselves.
    importers = {
        m: sorted(a for a in apps if a in deps) for m, deps in graph.items() if m not in apps and apps & deps
    }
    assert importers == {}, importers


@pytest.mark.parametrize(("overrides", "optimum"), [(["experiment=bounded"], 2694.0), ([], None)])
def test_evaluations_give_the_share_of_the_optimum_with_bounded_thrust(tmp_path, overrides, optimum):
    run = tmp_path / "run"
    train(_cfg(*overrides, "algo.episodes=4", "eval.every_episodes=2", *FAST[:-1]), run_dir=run)
    events = EventAccumulator(str(run / "tensorboard"), size_guidance={"scalars": 0})
    events.Reload()
    returns = [e.value for e in events.Scalars("eval/return")]
    assert len(returns) == 2
    if optimum is None:  # unbounded thrust: the bound is the ceiling, PD the reference
        assert "eval/pct_of_optimum" not in events.Tags()["scalars"]
        return
    shares = [e.value for e in events.Scalars("eval/pct_of_optimum")]
    np.testing.assert_allclose(shares, [100 * r / optimum for r in returns], rtol=1e-6)


class _ClosingSpy:
    """Wraps a run's real logger and notes each ``close`` and how the run ended."""

    closed: list[tuple[str, str]] = []

    def __init__(self, logger, run_dir: Path) -> None:
        self.logger, self.run_dir = logger, run_dir

    def __getattr__(self, name):
        return getattr(self.logger, name)

    def close(self, status: str) -> None:
        _ClosingSpy.closed.append((self.run_dir.name, status))
        self.logger.close(status)


def test_every_run_closes_its_logger_once_saying_how_it_ended(tmp_path, monkeypatch):
    """RunRecord.close() flushed the logger but never closed it, so a backend holding a run open (W&B's
    service, MLflow's RUNNING status) was never finished, least of all on a failed or stopped run.
    Three agents trained together: agent 1 diverges (its weights turn NaN), agent 2 finishes its
    budget, agent 0 is stopped by SIGTERM afterwards; each logger is closed once, told which."""
    import os
    import signal

    from drone_torchrl.training import run as run_module
    from drone_torchrl.training.signals import TrainingStopped

    real = run_module.make_logger
    monkeypatch.setattr(run_module, "make_logger", lambda cfg, d, at: _ClosingSpy(real(cfg, d, at), d))
    _ClosingSpy.closed = []
    jobs = [
        prepare(
            _cfg(f"algo.episodes={budget}", "checkpoint.every_episodes=2", *FAST, f"seed={s}"),
            tmp_path / f"a{s}",
        )
        for s, budget in enumerate((12, 12, 4))
    ]
    trainer = Trainer(jobs)
    trainer.step([0, 1, 2], 1)
    with torch.no_grad():
        trainer.population.policy.params.get(("mean", "bias"))[1] = float("nan")
    record = run_module.RunRecord.record

    def record_and_stop(self, episodes, metrics):
        record(self, episodes, metrics)
        if self.run_dir.name == "a0" and self.updates_done == 8:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(run_module.RunRecord, "record", record_and_stop)
    with pytest.raises(TrainingStopped):
        trainer.train()
    assert sorted(_ClosingSpy.closed) == [("a0", "stopped"), ("a1", "failed"), ("a2", "finished")]


@pytest.mark.parametrize("backend", BACKENDS)
def test_stop_return_ends_the_run_at_the_first_evaluation_that_reaches_it(tmp_path, backend, capsys):
    """eval.stop_return: the run ends at the first evaluation at or above it, with a final checkpoint.

    The same command then has nothing to do; with the key set to null the run trains on to its
    budget and ends as the run that never stopped.
    """
    common = (f"backend={backend}", "algo.episodes=8", "eval.every_episodes=2", *FAST)
    whole = tmp_path / "whole"
    train(_cfg(*common), run_dir=whole)
    evals = _tb_points(whole, "eval/return")
    assert sorted(evals) == [2, 4, 6, 8]
    # best.pt: the first evaluation at the best return (a later equal one does not replace it).
    kept = load_checkpoint(whole / "checkpoints" / "best.pt")
    best, first_best = kept["best_eval_return"], kept["episodes_done"]
    assert evals[first_best] == pytest.approx(best) and first_best < 8  # else the test shows no stop

    run = tmp_path / "run"
    train(_cfg(*common, f"eval.stop_return={best}"), run_dir=run)
    assert "eval.stop_return" in capsys.readouterr().out
    assert len(read_episodes(run / "episodes.csv")[0]["return"]) == first_best
    checkpoint = load_checkpoint(run / "checkpoints" / "last.pt")
    assert checkpoint["episodes_done"] == first_best and checkpoint["final"] is not None
    assert checkpoint["stopped_at_return"] == best
    assert job_status(run)[0] == "finished"
    train(_cfg(*common, f"eval.stop_return={best}"), run_dir=run)
    assert "already finished" in capsys.readouterr().out

    raised = (f"eval.stop_return={best + 1}", f"resume={run}")  # above the return it stopped at: trains on
    train_jobs([prepare(_cfg(*common, *raised), run_dir=run, requested=raised)])
    np.testing.assert_array_equal(
        read_episodes(run / "episodes.csv")[0]["return"], read_episodes(whole / "episodes.csv")[0]["return"]
    )
    assert _tb_points(run, "eval/return") == evals
