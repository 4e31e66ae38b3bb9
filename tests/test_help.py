"""``--help`` of the console commands: the page made from conf/ (groups, options, every key with its
value and meaning), named after the command, quick, and without torch."""

import shutil
import subprocess
import sys
import time
from importlib.metadata import entry_points
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from drone_torchrl.config import config_dir

CONF = Path(config_dir())
# Generous for a loaded CI machine; on an idle 2-core machine a page takes about 1 s (torch alone
# takes 2-3 s to import, so a page that imported it would not make it).
MAX_SECONDS = 3.0
HYDRA_PAGE = "is powered by Hydra"
# command -> its primary config, and the groups it takes beyond those its defaults list chooses.
APPS = {
    "drone-train": ("config", {"sweep"}),
    "drone-eval": ("eval", set()),
    "drone-export": ("export", set()),
}


def console(name: str) -> str:
    """The installed console script ``name`` (beside this interpreter, else on PATH)."""
    here = Path(sys.executable).parent / name
    found = str(here) if here.is_file() else shutil.which(name)
    if found is None:
        pytest.skip(f"{name} is not installed")
    return found


def entry_point(name: str):
    """The function pyproject's [project.scripts] names for console command ``name``."""
    (command,) = entry_points(group="console_scripts", name=name)
    return command.load()


def run_console(name: str, *args: str) -> tuple[subprocess.CompletedProcess, float]:
    start = time.perf_counter()
    done = subprocess.run([console(name), *args], capture_output=True, text=True, timeout=60)
    return done, time.perf_counter() - start


def composed(config: str, overrides: list[str] | None = None):
    """The config as the command composes it, with the real schemas: (config without hydra, choices)."""
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose(config, overrides=overrides or [], return_hydra_config=True)
    choices = dict(cfg.hydra.runtime.choices)
    values = OmegaConf.to_container(cfg, resolve=False)
    del values["hydra"]
    return values, choices


def leaves(node, prefix=""):
    for key, value in node.items():
        if isinstance(value, dict) and value:
            yield from leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def typed(value) -> str:
    """How a value is typed on the command line."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(typed(v) for v in value) + "]"
    if value == {}:
        return "{}"
    return str(value)


def check_page(text: str, prog: str, config: str, overrides: list[str] | None = None) -> None:
    """Every group with all its options, and every key with its value, are on the page; with the
    default config, every key with a meaning too (each option file need not comment every key)."""
    assert text.startswith(f"{prog}: "), text[:200]
    assert HYDRA_PAGE not in text and "train is powered" not in text
    values, choices = composed(config, overrides)
    lines = text.splitlines()
    groups = {g for g in choices if "/" not in g} | APPS[prog][1]
    for group in groups:
        options = sorted(p.stem for p in (CONF / group).glob("*.yaml"))
        chosen = choices.get(group)
        marker = group if chosen is not None else f"+{group}"
        line = next((x for x in lines if x.startswith(f"  {marker}: ")), None)
        assert line is not None, f"group {group} missing from the page"
        assert line.split(": ", 1)[1].split(" | ") == [f"{o}*" if o == chosen else o for o in options]
    keys = list(leaves(values))
    assert len(keys) >= 4
    for key, value in keys:
        line = next((x for x in lines if f"{x} ".startswith(f"  {key}={typed(value)} ")), None)
        assert line is not None, f"{key}={typed(value)} missing from the page"
        meaning = line.split(f"{key}={typed(value)}", 1)[1].strip()
        assert meaning or overrides, f"{key} has no meaning on the page (a comment in its conf/ file)"


@pytest.mark.parametrize("prog", list(APPS))
def test_console_help_page_is_quick_and_lists_every_group_and_key(prog):
    done, seconds = run_console(prog, "--help")
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    check_page(done.stdout, prog, APPS[prog][0])
    assert seconds < MAX_SECONDS, f"{prog} --help took {seconds:.2f} s"


def test_help_page_follows_the_command_lines_choices(command_here, tmp_path):
    # -h as --help; algo=ppo: PPO's keys and values (its own option file's), ppo marked as chosen.
    done = command_here(
        entry_point("drone-train"), "drone-train", "algo=ppo", "algo.lr=0.003", "-h", cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr
    check_page(done.stdout, "drone-train", "config", ["algo=ppo", "algo.lr=0.003"])
    # ppo.yaml leaves algo.lr uncommented: the same key's comment in another algo option.
    assert "  algo.lr=0.003 " in done.stdout and "  algo.clip_epsilon=0.2" in done.stdout
    assert list(tmp_path.iterdir()) == []  # no run folder, no log


def test_help_page_refuses_an_override_that_does_not_compose_in_one_line(command_here, tmp_path):
    done = command_here(entry_point("drone-eval"), "drone-eval", "disturbance=gale", "--help", cwd=tmp_path)
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr.startswith("drone-eval: error: ") and "disturbance/gale" in done.stderr
    assert "Available options in 'disturbance': mild, none, strong" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("prog", [*APPS, "drone-report"])
def test_help_imports_no_torch(prog):
    # The function pyproject's [project.scripts] names for the command, called as its script does.
    code = (
        "import sys\n"
        "from importlib.metadata import entry_points\n"
        f"sys.argv = [{prog!r}, '--help']\n"
        f"(command,) = entry_points(group='console_scripts', name={prog!r})\n"
        "try:\n    command.load()()\nexcept SystemExit as stop:\n    assert stop.code in (0, None), stop.code\n"
        "print('torch' in sys.modules, file=sys.stderr)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert prog in done.stdout
    assert done.stderr.strip() == "False"


def test_import_drone_torchrl_registers_the_gym_env_without_torch():
    code = (
        "import sys\nimport drone_torchrl\nprint('torch' in sys.modules)\n"
        "import gymnasium\nenv = gymnasium.make('Drone2D-v0')\nprint(env.reset(seed=0)[0].shape)\n"
        # drone_torchrl.envs loads its classes and submodules on first use, as an eager package had them.
        "print(drone_torchrl.envs.DroneEnv.__name__, drone_torchrl.envs.disturbances.Disturbance.__name__)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["False", "(6,)", "DroneEnv Disturbance"]


def test_drone_report_help_is_quick():
    done, seconds = run_console("drone-report", "--help")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: drone-report") and "--return-threshold" in done.stdout
    assert seconds < MAX_SECONDS, f"drone-report --help took {seconds:.2f} s"


def test_key_comments_reads_inline_comments_and_the_block_above():
    from drone_torchrl.apps.help import key_comments

    text = (
        "# header of the file\n"
        "defaults:\n"
        "  - _self_   # not a key\n"
        "\n"
        "seed: 0   # the seed\n"
        "# Which one trains (docs/engines.md):\n"
        "# fast: the C++ engine.\n"
        "backend: fast\n"
        "plain: 1\n"
        "eval:\n"
        "  episodes: 10  # per evaluation\n"
        "  # End the run at this return (a\n"
        "  # threshold). null: never.\n"
        "  stop: null\n"
    )
    assert key_comments(text) == {
        "seed": "the seed",
        "backend": "Which one trains (docs/engines.md)",
        "eval.episodes": "per evaluation",
        "eval.stop": "End the run at this return (a threshold).",
    }
