"""Where drone-eval and drone-export put what they make.

drone-eval writes the table it prints as ``results.csv`` (one row per policy) and ``results.json``
(what was flown, and the rows) in its output folder; drone-export without ``output=`` writes into
the checkpoint's run folder (``<run>/export/``), never into the folder it was started from.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import re
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from drone_torchrl import export
from drone_torchrl.apps import evaluate as eval_app
from drone_torchrl.apps import export as export_app
from drone_torchrl.config import config_dir, validate
from drone_torchrl.training.trainer import train, train_population

# A tiny run with bounded thrust: drone-eval then prints the % of the optimum too.
TINY = ["algo.episodes=2", "env.max_steps=20", "eval.episodes=1", "eval.video=false", "progress=false"]
BOUNDED = ["env.max_thrust=1.0"]
# The files drone-eval writes beside its plot (docs/training.md names them).
TABLE_NAME, SETTINGS_NAME = "results.csv", "results.json"

# One policy's line of drone-eval's table (comparison.run_eval), every figure captured.
LINE = re.compile(
    r"(?P<policy>.+): return (?P<return_mean>\S+) \+- (?P<return_std>\S+) "
    r"\((?P<pct_of_max>\S+)% of (?P<ceiling>\d+), (?:(?P<pct_of_optimum>\S+)% of the optimum \d+, )?"
    r"(?P<pct_of_pd>\S+)% of PD\), length (?P<length_mean>\S+), time in zone (?P<time_in_zone>\S+)%, "
    r"first in the zone at step (?P<first_zone_step_mean>\S+) \(reached in (?P<reached_fraction>\S+)%\), "
    r"thrust mean (?P<thrust_mean>\S+) max (?P<thrust_max>\S+) x weight, "
    r"negative thrust (?P<negative_thrust_fraction>\S+)%; episode ends: (?P<ends>.+) \(NONE = truncated"
)
# The printed figures: column -> (how many decimals, the factor printed: a fraction as a percentage).
PRINTED = {
    "return_mean": (1, 1),
    "return_std": (1, 1),
    "pct_of_max": (1, 1),
    "pct_of_optimum": (1, 1),
    "pct_of_pd": (1, 1),
    "length_mean": (1, 1),
    "time_in_zone": (1, 100),
    "first_zone_step_mean": (1, 1),
    "reached_fraction": (0, 100),
    "thrust_mean": (3, 1),
    "thrust_max": (3, 1),
    "negative_thrust_fraction": (1, 100),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """A finished tiny run; a tiny population run of two agents where pyarrow is installed."""
    root = tmp_path_factory.mktemp("runs")
    with initialize_config_dir(config_dir(), version_base="1.3"):
        train(compose("config", overrides=[*TINY, *BOUNDED]), root / "run")
        agents = [compose("config", overrides=[*TINY, f"seed={seed}"]) for seed in (0, 1)]
    out = {"run": root / "run"}
    if importlib.util.find_spec("pyarrow") is not None:
        for cfg in agents:
            validate(cfg)
        train_population(agents, ["seed=0", "seed=1"], root / "population")
        out["population"] = root / "population"
    return out


@pytest.fixture
def quick_latency(monkeypatch):
    """drone-export's latency figures from a few calls (what is tested here is where it writes)."""
    latencies = export.latencies
    monkeypatch.setattr(export, "latencies", lambda passes: latencies(passes, repeats=1, calls=2, warmup=0))


def test_drone_eval_writes_the_printed_table(runs, tmp_path, command_here):
    """results.csv holds the printed figures, row by row; results.json the same rows and the settings."""
    out = tmp_path / "eval"
    proc = command_here(
        eval_app.run,
        "drone-eval",
        f"checkpoint={runs['run']}",
        "episodes=3",
        "seed=4",
        "video=false",
        "plot=false",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    printed = [m.groupdict() for m in map(LINE.match, proc.stdout.splitlines()) if m]
    assert [p["policy"] for p in printed] == ["checkpoint (last.pt, episode 2)", "PD controller"], proc.stdout
    assert f"wrote {out / TABLE_NAME} and {out / SETTINGS_NAME}" in proc.stdout.splitlines()

    with open(out / TABLE_NAME, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [row["policy"] for row in rows] == [p["policy"] for p in printed]
    for row, line in zip(rows, printed, strict=True):
        for column, (decimals, factor) in PRINTED.items():
            assert f"{factor * float(row[column]):.{decimals}f}" == line[column], (column, row, line)
        ends = dict(part.split() for part in line["ends"].split(", "))
        assert {k: int(row[f"ends_{k}"]) for k in ends} == {k: int(v) for k, v in ends.items()}
        assert sum(int(row[c]) for c in row if c.startswith("ends_")) == 3  # every episode ends once
        assert int(row["crashes"]) == sum(int(v) for k, v in ends.items() if k != "NONE")
    pd = rows[1]
    assert float(pd["pct_of_pd"]) == 100.0
    assert float(rows[0]["pct_of_pd"]) == pytest.approx(
        100 * float(rows[0]["return_mean"]) / float(pd["return_mean"])
    )

    document = json.loads((out / SETTINGS_NAME).read_text())
    assert (document["episodes"], document["seed"], document["agent"]) == (3, 4, None)
    assert document["checkpoint"] == str(runs["run"] / "checkpoints" / "last.pt")
    assert document["env"]["max_thrust"] == 1.0 and document["env"]["max_steps"] == 20
    assert document["ceiling"] == 200.0 and document["optimum"] == pytest.approx(
        100 * float(pd["return_mean"]) / float(pd["pct_of_optimum"])
    )
    assert [p["policy"] for p in document["policies"]] == [row["policy"] for row in rows]
    for entry, row in zip(document["policies"], rows, strict=True):
        for column, value in row.items():
            expected = entry[column] if entry[column] is not None else math.nan
            assert (
                value == str(expected)
                if column == "policy"
                else float(value) == pytest.approx(expected, nan_ok=True)
            ), column
    assert not list(out.glob("*.tmp"))  # written through a temporary file and a rename


def test_drone_eval_of_the_pd_controller_writes_no_optimum_as_null(tmp_path, command_here):
    """Unbounded thrust has no optimum: nan in the CSV (pandas reads NaN), null in the JSON."""
    out = tmp_path / "eval"
    proc = command_here(
        eval_app.run,
        "drone-eval",
        "episodes=2",
        "env.max_steps=20",
        "video=false",
        "plot=false",
        f"hydra.run.dir={out}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    with open(out / TABLE_NAME, newline="") as f:
        (row,) = csv.DictReader(f)
    assert row["policy"] == "PD controller" and math.isnan(float(row["pct_of_optimum"]))
    document = json.loads((out / SETTINGS_NAME).read_text())
    assert document["optimum"] is None and document["policies"][0]["pct_of_optimum"] is None
    assert document["checkpoint"] is None


def test_drone_export_without_output_writes_into_the_run_folder(runs, tmp_path, command_here, quick_latency):
    """checkpoint=<run>: <run>/export/last.pt2; checkpoints/best.pt: best.pt2; nothing in the working folder."""
    run = runs["run"]
    for checkpoint, name in ((run, "last.pt2"), (run / "checkpoints" / "best.pt", "best.pt2")):
        proc = command_here(export_app.run, "drone-export", f"checkpoint={checkpoint}", cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.splitlines()[0] == f"wrote {run / 'export' / name}"
        assert (run / "export" / name).stat().st_size > 0
    assert sorted(p.name for p in (run / "export").iterdir()) == ["best.pt2", "last.pt2"]
    assert list(tmp_path.iterdir()) == []
    # output= still writes where it says.
    proc = command_here(export_app.run, "drone-export", f"checkpoint={run}", "output=here.pt2", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["here.pt2"]


def test_drone_export_names_a_population_agent_s_file_after_it(runs, tmp_path, command_here, quick_latency):
    """agent=K of a population run: <run>/export/last_agent<K>.pt2, one file per agent."""
    if "population" not in runs:
        pytest.skip("a population run needs pyarrow: pip install 'drone_torchrl[population]'")
    run = runs["population"]
    for agent in (0, 1):
        proc = command_here(
            export_app.run, "drone-export", f"checkpoint={run}", f"agent={agent}", cwd=tmp_path
        )
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.splitlines()[0] == f"wrote {run / 'export' / f'last_agent{agent}.pt2'}"
    assert sorted(p.name for p in (run / "export").iterdir()) == ["last_agent0.pt2", "last_agent1.pt2"]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("checkpoint", "format", "agent", "expected"),
    [
        ("r/checkpoints/last.pt", "pt2", None, "r/export/last.pt2"),
        ("r/checkpoints/best.pt", "onnx", None, "r/export/best.onnx"),
        ("r/checkpoints/last.pt", "pt2", 3, "r/export/last_agent3.pt2"),
        ("models/mine.pt", "pt2", None, "models/export/mine.pt2"),  # a file outside a run's checkpoints/
    ],
)
def test_the_default_output_is_in_the_run_folder(checkpoint, format, agent, expected):
    assert export.default_output(Path(checkpoint), format, agent) == Path(expected)
