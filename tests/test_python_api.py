"""drone_torchrl.train and drone_torchrl.evaluate: drone-train's and drone-eval's work from Python.

The same numbers as the commands for the same config, twice in one process, the process left as
found, the trained policy usable, a bad override refused in one line with nothing written.
"""

import datetime
import logging
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.version import VersionBase

import drone_torchrl
from drone_torchrl.apps import evaluate as evaluate_app
from drone_torchrl.envs.drone_env import DroneEnv
from drone_torchrl.export import actor_commands
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import read_episodes

ROOT = Path(__file__).resolve().parents[1]
TINY = ("algo.episodes=2", "env.max_steps=20", "eval.episodes=1", "eval.video=false", "progress=false")
# The hover observation and two others: a spread of what the policy sees.
OBSERVATIONS = torch.tensor(
    [[0.0, 0.0, 2.7, 0.0, 0.0, 0.0], [0.5, -1.0, 1.0, 2.0, 0.3, -0.5], [-1.5, 0.2, 3.5, -1.0, -0.6, 1.0]]
)


def _episodes(run: Path) -> dict[str, list]:
    """The run's episodes.csv columns, its wall clock left out (it differs between any two runs)."""
    columns = read_episodes(run / "episodes.csv")[0]
    return {key: list(values) for key, values in columns.items() if key != "wall_clock_s"}


def _numbers(metrics: dict[str, float]) -> dict[str, float]:
    return {key: value for key, value in metrics.items() if key != "wall_clock_s"}


def _process_state() -> dict:
    root = logging.getLogger()
    return {
        "cwd": os.getcwd(),
        "handlers": list(root.handlers),
        "root level": root.level,
        "levels": {
            name: logger.level
            for name, logger in logging.root.manager.loggerDict.items()
            if hasattr(logger, "level")
        },
        "signals": {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGUSR1, signal.SIGINT)},
        "GlobalHydra": GlobalHydra.instance().is_initialized(),
        "HydraConfig": HydraConfig.initialized(),
        "version_base": VersionBase.instance().getbase(),
        "threads": torch.get_num_threads(),
        "rng": torch.get_rng_state(),
    }


def _assert_same_state(before: dict, after: dict) -> None:
    assert torch.equal(before.pop("rng"), after.pop("rng")), "torch's global random state changed"
    # Loggers first made during the call (a module imported then) start at NOTSET: not a change.
    after["levels"] = {name: level for name, level in after["levels"].items() if name in before["levels"]}
    assert after == before


# Slow stage: drone-train in a process of its own (seconds of imports); the default suite stays near 5 minutes.
@pytest.mark.slow
def test_train_gives_the_numbers_of_drone_train(tmp_path):
    """The same config, from the command line (a process of its own) and from Python: the same run."""
    cli, api = tmp_path / "cli", tmp_path / "api"
    drone_train = Path(sys.executable).with_name("drone-train")
    command = (
        [str(drone_train)] if drone_train.exists() else [sys.executable, "-m", "drone_torchrl.apps.train"]
    )
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
    done = subprocess.run(
        [*command, *TINY, "seed=3", "algo.lr=3e-3", f"hydra.run.dir={cli}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert done.returncode == 0, done.stderr

    result = drone_torchrl.train(*TINY, seed=3, **{"algo.lr": 3e-3}, run_dir=api)

    assert result.run_dir == api
    saved = load_checkpoint(cli / "checkpoints" / "last.pt")
    assert _numbers(result.metrics) == _numbers(saved["final"])
    assert result.final_return == saved["final"]["final_return"]
    assert result.eval_return == saved["final"]["eval_return"]
    assert _episodes(api) == _episodes(cli)
    assert len(_episodes(api)["return"]) == 2
    assert (api / "config.yaml").read_text().splitlines()[1:] == (
        cli / "config.yaml"
    ).read_text().splitlines()[1:]
    mine = load_checkpoint(result.checkpoint)
    assert mine["actor"].keys() == saved["actor"].keys()
    for key, weights in saved["actor"].items():
        assert torch.equal(mine["actor"][key], weights), key
    assert result.config.seed == 3 and result.config.algo.lr == 3e-3


def test_twice_in_one_process_the_same_seed_gives_the_same_run_and_another_seed_another(tmp_path):
    before = _process_state()
    first = drone_torchrl.train(*TINY, "seed=5", run_dir=tmp_path / "a")
    again = drone_torchrl.train(*TINY, seed=5, run_dir=tmp_path / "b")
    other = drone_torchrl.train(*TINY, seed=6, run_dir=tmp_path / "c")
    _assert_same_state(before, _process_state())

    assert _numbers(first.metrics) == _numbers(again.metrics)
    assert _episodes(tmp_path / "a") == _episodes(tmp_path / "b")
    assert torch.equal(first.policy(OBSERVATIONS), again.policy(OBSERVATIONS))
    # Another seed: other starting weights, other episodes.
    assert not torch.equal(first.policy(OBSERVATIONS), other.policy(OBSERVATIONS))
    assert _episodes(tmp_path / "c") != _episodes(tmp_path / "a")


def test_the_process_is_left_as_found_inside_a_callers_hydra(tmp_path, monkeypatch):
    """A caller's own Hydra (its initialize, a HydraConfig of its app) is its own again afterwards."""
    (tmp_path / "conf").mkdir()
    (tmp_path / "conf" / "mine.yaml").write_text("answer: 42\n")
    monkeypatch.setattr(HydraConfig.instance(), "cfg", None)  # put back after the test
    with initialize_config_dir(str(tmp_path / "conf"), version_base="1.2", job_name="mine"):
        # As inside the caller's Hydra app: its job's config (its command line: answer=7).
        HydraConfig.instance().set_config(compose("mine", ["answer=7"], return_hydra_config=True))
        before = _process_state()
        result = drone_torchrl.train(*TINY, run_dir=tmp_path / "run")
        _assert_same_state(before, _process_state())
        assert compose("mine").answer == 42  # the caller's config folder, not drone_torchrl's
        assert HydraConfig.get().job.name == "mine"
        assert list(HydraConfig.get().overrides.task) == ["answer=7"]
    assert not GlobalHydra.instance().is_initialized()
    assert result.metrics["final_return"] == pytest.approx(sum(_episodes(tmp_path / "run")["return"]) / 2)


def test_a_run_folder_with_a_run_continues_it_taking_only_what_a_continued_run_takes(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    drone_torchrl.train(*TINY, run_dir=run)
    first = _episodes(run)
    with pytest.raises(drone_torchrl.ConfigError, match=r"algo.lr") as refused:
        drone_torchrl.train(*TINY, "algo.episodes=4", "algo.lr=1e-3", run_dir=run)  # a kept hyper-parameter
    assert "\n" not in str(refused.value)
    longer = drone_torchrl.train(*TINY, "algo.episodes=4", run_dir=run)
    assert longer.run_dir == run and longer.config.algo.episodes == 4
    assert _episodes(run)["episode"] == [0, 1, 2, 3]
    assert {key: values[:2] for key, values in _episodes(run).items()} == first
    # resume= names the run: it continues in its own folder, whatever the default folder would be.
    again = drone_torchrl.train(*TINY, "algo.episodes=6", resume=run)
    assert again.run_dir == run and len(_episodes(run)["episode"]) == 6
    assert not (tmp_path / "outputs").exists()


def test_the_returned_policy_acts_as_the_checkpoint(tmp_path):
    result = drone_torchrl.train(*TINY, "seed=2", run_dir=tmp_path / "run")
    saved = load_checkpoint(tmp_path / "run" / "checkpoints" / "last.pt")
    for key, weights in saved["actor"].items():
        assert torch.equal(result.actor.state_dict()[key], weights), key

    commands = result.policy(OBSERVATIONS)
    assert commands.shape == (3, 2)
    # The deterministic action the actor takes (its Normal's mean) is what the policy gives.
    assert torch.equal(commands, actor_commands(result.actor, OBSERVATIONS, None))
    loc = result.actor.module[0](OBSERVATIONS)[0]
    assert torch.equal(commands, loc)

    # The actor reads a DroneEnv tensordict as TorchRL's rollout does.
    env = DroneEnv(batch_size=[4], max_steps=20)
    env.set_seed(0)
    rollout = env.rollout(5, result.actor)
    env.close()
    assert rollout["action"].shape == (4, 5, 2)


def test_evaluate_returns_the_numbers_drone_eval_prints(tmp_path, command_here, capfd):
    run = drone_torchrl.train(*TINY, run_dir=tmp_path / "run").run_dir
    done = command_here(
        evaluate_app.run,
        "drone-eval",
        f"checkpoint={run}",
        "episodes=3",
        "video=false",
        "plot=false",
        f"hydra.run.dir={tmp_path / 'eval'}",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr

    result = drone_torchrl.evaluate(checkpoint=run, episodes=3, video=False, plot=False)
    printed = capfd.readouterr().out

    assert result.plot is None and result.video is None
    assert list(result.results) == ["checkpoint (last.pt, episode 2)", "PD controller"]
    for name, row in result.results.items():
        line = next(line for line in done.stdout.splitlines() if line.startswith(f"{name}: "))
        assert line in printed.splitlines()  # the very table drone-eval prints
        numbers = re.match(r".*: return (\S+) \+- (\S+) .*, length (\S+), time in zone (\S+)%", line)
        assert float(numbers[1]) == round(row["return_mean"], 1)
        assert float(numbers[2]) == round(row["return_std"], 1)
        assert float(numbers[3]) == round(row["length_mean"], 1)
        assert float(numbers[4]) == round(100 * row["time_in_zone"], 1)
    assert result.policy is result.results["checkpoint (last.pt, episode 2)"]
    assert result.pd["return_mean"] == 20.0  # the PD controller stays up all 20 steps, outside the zone


def test_evaluate_writes_its_plot_where_asked_and_refuses_what_drone_eval_refuses(tmp_path):
    run = drone_torchrl.train(*TINY, run_dir=tmp_path / "run").run_dir
    result = drone_torchrl.evaluate(checkpoint=run, episodes=1, video=False, out_dir=tmp_path / "eval")
    assert result.plot == tmp_path / "eval" / "trajectory.png" and result.plot.is_file()
    # A checkpoint flies in its own env: an env override is refused, as on drone-eval's command line.
    with pytest.raises(
        drone_torchrl.ConfigError, match=r"changes env.max_steps 20 -> 10: drop those overrides"
    ):
        drone_torchrl.evaluate(checkpoint=run, plot=False, video=False, **{"env.max_steps": 10})


@pytest.mark.parametrize(
    ("overrides", "values", "message"),
    [
        (("algo.lr=-1",), {}, r"^algo.lr=-1"),
        (("algo.lrr=1",), {}, r"^algo.lrr is not a config key; did you mean algo.lr\?"),
        ((), {"algo": "nope"}, r"^algo='nope' is not allowed; expected one of \["),
        ((), {"algo": {"lr": "fast"}}, r"^algo.lr='fast'"),
        (("seed=0,1",), {}, r"^seed=0,1 is a sweep"),
        (("hydra.job.chdir=true",), {}, r"^hydra.job.chdir=true is a Hydra setting"),
        (("-m",), {}, r"^-m is a command-line flag"),
        ((3,), {}, r"takes Hydra override strings"),
        ((), {"seed": object()}, r"^seed=<object"),
        ((), {"device": "mps"}, r"^device='mps' is not allowed"),
        ((), {"device": 3}, r"^device=3 is not allowed"),
        ((), {"run_dir": 3}, r"takes a folder path"),
        (("hydra.run.dir=null",), {}, r"^hydra.run.dir=null is not allowed; expected a folder path"),
        (("algo.lr=3e-4",), {"algo": {"lr": 1e-3}, "run_dir": "x", "hydra.run.dir": "y"}, r"given twice"),
    ],
)
def test_a_bad_override_is_one_line_and_writes_nothing(tmp_path, monkeypatch, overrides, values, message):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(drone_torchrl.ConfigError, match=message) as refused:
        drone_torchrl.train(*TINY, *overrides, **values)
    assert "\n" not in str(refused.value)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(drone_torchrl.ConfigError, match=r"^checkpoint='.*missing'") as refused:
        drone_torchrl.evaluate(checkpoint=tmp_path / "missing", out_dir=tmp_path / "eval")
    assert "\n" not in str(refused.value)
    assert list(tmp_path.iterdir()) == []


def test_the_default_run_folder_is_outputs_date_time_and_a_second_run_that_second_gets_its_own(
    tmp_path, monkeypatch
):
    class Frozen(datetime.datetime):
        @classmethod
        def now(cls, tz=None):
            return cls(2030, 1, 2, 3, 4, 5)

    monkeypatch.setattr("hydra.core.utils.datetime", Frozen)  # Hydra's ${now:...}
    monkeypatch.chdir(tmp_path)
    first = drone_torchrl.train(*TINY)
    second = drone_torchrl.train(*TINY)
    assert first.run_dir == tmp_path / "outputs" / "2030-01-02" / "03-04-05"
    assert second.run_dir == tmp_path / "outputs" / "2030-01-02" / "03-04-05-1"
    # The second trained a run of its own rather than continuing the first.
    assert len(_episodes(second.run_dir)["return"]) == 2
    assert _numbers(second.metrics) == _numbers(first.metrics)


@pytest.mark.parametrize(
    "value",
    [
        "plain",
        "with space, comma=equals: colon",
        "it's",
        r"back\slash",
        "ends with\\",
        "quote\\'s escape",
        "",
        "${seed}",
        3e-4,
        -2,
        math.inf,
        None,
        True,
        [64, 64],
        ["a", 1.5],
        Path("/a b/c"),
    ],
)
def test_a_keyword_value_reaches_hydra_as_that_value(value):
    from drone_torchrl.api import _hydra_value

    (override,) = OverridesParser.create().parse_overrides([f"key={_hydra_value('key', value)}"])
    expected = os.fspath(value) if isinstance(value, Path) else value
    assert override.value() == expected
    assert type(override.value()) is type(expected)


def test_the_entry_points_are_the_package_s():
    from drone_torchrl import api

    assert {"train", "evaluate", "TrainResult", "EvalResult", "ConfigError"} <= set(drone_torchrl.__all__)
    assert drone_torchrl.train is api.train and drone_torchrl.evaluate is api.evaluate
    assert drone_torchrl.TrainResult is api.TrainResult and drone_torchrl.EvalResult is api.EvalResult
    assert drone_torchrl.ConfigError is api.ConfigError
    assert {"train", "evaluate"} <= set(dir(drone_torchrl))
    with pytest.raises(AttributeError, match="no attribute 'trian'"):
        drone_torchrl.trian  # noqa: B018


# A process of its own: seconds of imports.
@pytest.mark.slow
def test_the_entry_points_load_when_first_used():
    code = (
        "import sys, drone_torchrl; assert 'drone_torchrl.api' not in sys.modules; "
        "drone_torchrl.train; assert 'drone_torchrl.api' in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_the_python_page_has_a_block_the_docs_test_runs():
    page = (ROOT / "docs" / "python.md").read_text()
    assert "<!-- docs-test: run -->\n```python\n" in page
