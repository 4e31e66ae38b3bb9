"""drone-train / drone-eval: configs, validation, a smoke run per preset, resume, and learning."""

import inspect
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from drone_torchrl.config import ENV_ARGS, ConfigError, config_dir, validate
from drone_torchrl.envs import DroneEnv, disturbances
from drone_torchrl.envs.params import PARAM_NAMES, DroneParams
from drone_torchrl.io.checkpoint import load_checkpoint
from drone_torchrl.io.episodes_csv import CSV_COLUMNS, read_episodes
from drone_torchrl.training.trainer import train

FAST = ["eval.episodes=2", "eval.video=false", "progress=false"]
BACKENDS = ["reference", "fast"]


def _cfg(*overrides: str, name: str = "config"):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose(name, overrides=list(overrides))


def test_defaults_are_the_paper():
    cfg = _cfg()
    assert cfg.algo.lr == 1e-4 and cfg.algo.gamma == 0.99
    assert cfg.algo.episodes == 6000 and cfg.algo.episodes_per_update == 1
    assert cfg.model.distribution == "normal" and cfg.env.max_thrust is None
    assert list(cfg.model.hidden_sizes) == [32, 32] and cfg.model.activation == "tanh"
    assert not cfg.algo.discount_weight and not cfg.algo.normalize_returns and cfg.algo.baseline == "none"
    assert cfg.seed == 0
    # Every DroneEnv argument that describes the drone or the episode is a config key, with the
    # env's own default: DroneParams' fields (its keywords) and the episode's arguments (the process
    # settings batch_size/device/render_* are not).
    params = inspect.signature(DroneEnv.__init__).parameters
    process = ("self", "batch_size", "params", "device", "render_mode", "render_index", "overrides")
    episode = [n for n in params if n not in process]
    assert list(ENV_ARGS) == [*PARAM_NAMES, *episode]
    defaults = {**asdict(DroneParams()), **{n: params[n].default for n in episode if n != "disturbance"}}
    assert {n: cfg.env[n] for n in defaults} == defaults
    # The env's default disturbance (None) is the nominal drone, which disturbance=none spells out.
    assert params["disturbance"].default is None
    assert disturbances.make(dict(cfg.env.disturbance)) == disturbances.Disturbance()
    validate(cfg)


def test_presets_compose():
    bounded = _cfg("experiment=bounded")
    assert bounded.env.max_thrust == 1.0 and bounded.model.distribution == "tanh_normal"
    assert _cfg("experiment=paper") == _cfg()
    validate(bounded)
    ev = _cfg(name="eval")
    assert ev.checkpoint is None and ev.env.max_steps == 300


@pytest.mark.parametrize(
    ("override", "key"),
    [
        ("algo.gamma=1.5", "algo.gamma"),
        ("algo.gamma=-0.1", "algo.gamma"),
        ("algo.lr=0", "algo.lr"),
        ("algo.lr=-1e-4", "algo.lr"),
        ("algo.episodes=0", "algo.episodes"),
        ("algo.episodes_per_update=0", "algo.episodes_per_update"),
        ("algo.baseline=critic", "algo.baseline"),
        ("model.distribution=beta", "model.distribution"),
        ("model.distribution=tanh_normal", "model.distribution"),
        ("model.activation=sigmoid", "model.activation"),
        ("model.hidden_sizes=[]", "model.hidden_sizes"),
        ("env.mass=-1", "env.mass"),
        ("env.max_thrust=0", "env.max_thrust"),
        ("env.reset_mode=sky", "env.reset_mode"),
        ("env.max_steps=0", "env.max_steps"),
        ("seed=-3", "seed"),
        ("eval.episodes=0", "eval.episodes"),
        ("checkpoint.every_episodes=0", "checkpoint.every_episodes"),
    ],
)
def test_bad_values_are_named(override, key):
    with pytest.raises(ConfigError, match=rf"^{key.replace('.', '[.]')}="):
        validate(_cfg(override))


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_cli_bad_value_is_one_line_and_nonzero(tmp_path):
    """The real command, refused: two processes side by side (each with its own run folder)."""
    cases = [
        ("drone_torchrl.apps.train", "algo.gamma=2"),
        ("drone_torchrl.apps.train", f"resume={tmp_path}/nope"),
    ]

    def refused(i: int) -> subprocess.CompletedProcess:
        module, override = cases[i]
        return subprocess.run(
            [sys.executable, "-m", module, override, f"hydra.run.dir={tmp_path}/run{i}"],
            capture_output=True,
            text=True,
            timeout=120,
        )

    with ThreadPoolExecutor(len(cases)) as pool:
        procs = list(pool.map(refused, range(len(cases))))
    for (_, override), proc in zip(cases, procs, strict=True):
        assert proc.returncode != 0
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert override.split("=")[0] in lines[0]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("preset", ["paper", "bounded"])
def test_smoke_run_writes_everything_and_resumes(tmp_path, preset, backend):
    run = tmp_path / preset
    cfg = _cfg(
        f"backend={backend}",
        f"experiment={preset}",
        "algo.episodes=6",
        "algo.episodes_per_update=2",
        "checkpoint.every_episodes=2",
        "eval.every_episodes=4",
        "eval.video=true",
        "env.max_steps=40",
        *FAST[:1],
        "progress=false",
    )
    train(cfg, run_dir=run)
    rows = read_episodes(run / "episodes.csv")[0]
    assert rows["episode"].tolist() == [0, 1, 2, 3, 4, 5]
    assert set(CSV_COLUMNS) <= set(rows)
    assert all(1 <= n <= 40 for n in rows["length"])
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))
    assert list((run / "videos").glob("*.mp4"))
    ckpt = load_checkpoint(run / "checkpoints" / "last.pt")
    assert ckpt["episodes_done"] == 6 and ckpt["updates_done"] == 3
    assert OmegaConf.create(ckpt["config"]).model.distribution == cfg.model.distribution

    # Resume from the run folder with a larger budget: the counter carries on, the CSV grows.
    train(_cfg(f"resume={run}", "algo.episodes=10", "progress=false"))
    rows = read_episodes(run / "episodes.csv")[0]
    assert rows["episode"].tolist() == list(range(10))
    assert load_checkpoint(run / "checkpoints" / "last.pt")["updates_done"] == 5


@pytest.mark.parametrize("backend", BACKENDS)
def test_resume_after_a_kill_repeats_only_episodes_since_the_checkpoint(tmp_path, backend):
    """A run stopped after its checkpoint at episode 4 and resumed equals one uninterrupted run."""
    common = [
        f"backend={backend}",
        "env.max_steps=30",
        "checkpoint.every_episodes=4",
        "eval.every_episodes=0",
        *FAST,
    ]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    train(_cfg("algo.episodes=8", *common), run_dir=whole)
    train(_cfg("algo.episodes=4", *common), run_dir=cut)
    train(_cfg(f"resume={cut}", "algo.episodes=8", "progress=false"))
    a, b = read_episodes(whole / "episodes.csv")[0], read_episodes(cut / "episodes.csv")[0]
    assert a["return"].tolist() == b["return"].tolist() and a["length"].tolist() == b["length"].tolist()
    wa = load_checkpoint(whole / "checkpoints" / "last.pt")["actor"]
    wb = load_checkpoint(cut / "checkpoints" / "last.pt")["actor"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


def test_drone_eval_compares_with_pd(tmp_path):
    from drone_torchrl.comparison import run_eval

    run = tmp_path / "run"
    train(_cfg("algo.episodes=2", "env.max_steps=20", *FAST), run_dir=run)
    results = run_eval(_cfg(f"checkpoint={run}", "episodes=3", "video=false", "plot=false", name="eval"))
    assert set(results) == {"checkpoint (last.pt, episode 2)", "PD controller"}
    pd = results["PD controller"]
    assert pd["causes"]["NONE"] == 3  # the PD controller survives every 20-step episode
    for r in results.values():  # % of the 10 x max_steps ceiling of this 20-step env
        assert r["pct_of_max"] == pytest.approx(100 * r["return_mean"] / 200)


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_reinforce_learns_to_stay_up(tmp_path, backend):
    """From the floor with zero-mean thrust the drone hits the floor after ~6 steps (z_n = -g dt^2
    n(n+1)/2 passes -0.05 m at n = 5); 150 updates at alpha 1e-3 must keep it up several times longer."""
    run = tmp_path / "learn"
    train(
        _cfg(
            f"backend={backend}",
            "algo.episodes=150",
            "algo.lr=1e-3",
            "env.max_steps=60",
            "eval.every_episodes=0",
            *FAST,
        ),
        run_dir=run,
    )
    lengths = np.array(read_episodes(run / "episodes.csv")[0]["length"])
    assert lengths[:25].mean() < 10
    assert lengths[-25:].mean() > 25


@pytest.mark.slow  # over 5 s on 2 cores: the default suite keeps to about 5 minutes
def test_console_scripts_run_from_any_folder(tmp_path):
    """The installed drone-train / drone-eval find their packaged configs outside the checkout."""
    from pathlib import Path

    bin_dir = Path(sys.executable).parent
    train_cmd, eval_cmd = bin_dir / "drone-train", bin_dir / "drone-eval"
    if not train_cmd.exists():
        pytest.skip("console scripts are not installed in this environment")
    env = {**__import__("os").environ, "SDL_VIDEODRIVER": "dummy", "SDL_AUDIODRIVER": "dummy"}
    run = tmp_path / "run"
    proc = subprocess.run(
        [
            str(train_cmd),
            "algo.episodes=2",
            "env.max_steps=10",
            "eval.video=false",
            f"hydra.run.dir={run}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=180,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    assert len(read_episodes(run / "episodes.csv")[0]["episode"]) == 2
    proc = subprocess.run(
        [
            str(eval_cmd),
            f"checkpoint={run}",
            "episodes=2",
            "video=false",
            f"hydra.run.dir={tmp_path / 'eval'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=180,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr
    assert "PD controller: return" in proc.stdout
    assert (tmp_path / "eval" / "trajectory.png").stat().st_size > 0


def test_checkpoints_from_before_later_keys_still_evaluate_and_resume(tmp_path):
    """A checkpoint whose config predates backend (and engine) and logger.every_updates: filled with the
    old behaviour (the reference's loop, one update per log)."""
    from drone_torchrl.comparison import run_eval

    run = tmp_path / "old"
    train(_cfg("backend=reference", "algo.episodes=2", "env.max_steps=20", *FAST), run_dir=run)
    path = run / "checkpoints" / "last.pt"
    ckpt = load_checkpoint(path)
    del ckpt["config"]["backend"]
    del ckpt["config"]["logger"]["every_updates"]
    torch.save(ckpt, path)
    results = run_eval(_cfg(f"checkpoint={run}", "episodes=2", "video=false", "plot=false", name="eval"))
    assert "checkpoint (last.pt, episode 2)" in results
    train(_cfg(f"resume={run}", "algo.episodes=3", "progress=false"))
    assert load_checkpoint(path)["episodes_done"] == 3


@pytest.mark.parametrize("backend", BACKENDS)
def test_progress_bar_shows_the_running_mean_return(tmp_path, capsys, backend):
    fast = [o for o in FAST if not o.startswith("progress")]
    train(
        _cfg(f"backend={backend}", "algo.episodes=3", "env.max_steps=10", "progress=true", *fast),
        run_dir=tmp_path,
    )
    err = capsys.readouterr().err
    assert "3/3" in err and "return(100)=" in err
    train(
        _cfg(f"backend={backend}", "algo.episodes=3", "env.max_steps=10", "progress=auto", *fast),
        run_dir=tmp_path / "q",
    )
    assert "return(100)=" not in capsys.readouterr().err  # quiet when stderr is not a terminal
