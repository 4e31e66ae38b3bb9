"""``logger=wandb`` in W&B's offline mode (nothing leaves the machine), read back from the run files.

W&B writes an offline run as ``<dir>/wandb/offline-run-<time>-<id>/run-<id>.wandb``: a LevelDB-style
log of protobuf ``Record``s (what ``wandb sync`` uploads). :func:`_records` reads it, so these tests
see what W&B would upload: every history row with its step, the config, and how the run exited.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from drone_torchrl.checks import ConfigError
from drone_torchrl.config import config_dir, validate

wandb = pytest.importorskip("wandb")
from test_run_record import FAST, _whole_and_killed_then_resumed  # noqa: E402
from wandb.proto import wandb_internal_pb2  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# The log's framing (LevelDB's): a 7-byte file header, then 32 KiB blocks of records, each with a
# 7-byte header (CRC-32, length, type); FULL holds a whole record, FIRST..LAST one split over blocks.
FILE_HEADER = struct.Struct("<4sHB")
RECORD_HEADER = struct.Struct("<IHB")
BLOCK = 32768
FULL, LAST = 1, 4


@pytest.fixture(autouse=True)
def offline(tmp_path, monkeypatch):
    """W&B offline and quiet, its settings and caches in the test's folder."""
    for name, value in {
        "WANDB_MODE": "offline",
        "WANDB_SILENT": "true",
        "WANDB_CONFIG_DIR": str(tmp_path / "wandb-config"),
        "WANDB_CACHE_DIR": str(tmp_path / "wandb-cache"),
        "WANDB_DATA_DIR": str(tmp_path / "wandb-data"),
    }.items():
        monkeypatch.setenv(name, value)


def _records(path: Path):
    data = path.read_bytes()
    ident, magic, _ = FILE_HEADER.unpack_from(data)
    assert ident == b":W&B" and magic == 0xBEE1, path
    pos, pending = FILE_HEADER.size, b""
    while pos + RECORD_HEADER.size <= len(data):
        room = BLOCK - pos % BLOCK
        if room < RECORD_HEADER.size:  # a block's tail too short for a header is padding
            pos += room
            continue
        _, length, kind = RECORD_HEADER.unpack_from(data, pos)
        if length == 0 and kind == 0:
            pos += room
            continue
        pending += data[pos + RECORD_HEADER.size : pos + RECORD_HEADER.size + length]
        pos += RECORD_HEADER.size + length
        if kind in (FULL, LAST):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(pending)
            pending = b""
            yield record


def _key(item) -> str:
    """A history, summary or config item's key: ``episode/return`` is kept as a nested key."""
    return item.key or "/".join(item.nested_key)


def _offline_runs(run_dir: Path) -> list[Path]:
    """The run's offline W&B files, oldest first (a resumed run adds one per process).

    ``finish`` hands the run's last records to W&B's service process and returns; the service
    writes them after. Its teardown (what happens when a process exits) waits until it has."""
    wandb.teardown()
    files = [p for p in (run_dir / "wandb" / "wandb").glob("offline-run-*/run-*.wandb")]
    return sorted(files, key=lambda p: p.parent.name)


def _history(files: list[Path]) -> tuple[list[int], dict[str, dict[int, float]], set[str], list[int]]:
    """W&B's steps in the order sent, ``{tag: {episodes: value}}`` (each step sent once), the run ids,
    and the exit codes."""
    steps, points, ids, exits = [], {}, set(), []
    for path in files:
        for record in _records(path):
            kind = record.WhichOneof("record_type")
            if kind == "run":
                ids.add(record.run.run_id)
            elif kind == "exit":
                exits.append(record.exit.exit_code)
            elif kind == "history":
                row = {_key(item): json.loads(item.value_json) for item in record.history.item}
                steps.append(row["_step"])
                assert row["episodes"] == row["_step"]  # the episodes axis is W&B's own step
                for tag, value in row.items():
                    if not tag.startswith("_") and tag != "episodes" and isinstance(value, int | float):
                        assert row["episodes"] not in points.setdefault(tag, {}), (tag, row)  # sent once
                        points[tag][row["episodes"]] = value
    return steps, points, ids, exits


def test_a_resumed_run_is_one_wandb_run_with_every_step_once(tmp_path):
    """Killed after logging episodes 5-6 past its checkpoint at 4, then resumed to 8: one W&B run id
    across the processes' files, W&B's step only grows, every step of 1..8 sent once with the
    uninterrupted run's values (REINFORCE retrains the skipped 5-6 exactly), the evaluation the
    interrupted process sent at 6 kept, and each process's exit recorded."""
    whole, cut = _whole_and_killed_then_resumed(tmp_path, "logger=wandb")
    steps, expected, ids, exits = _history(_offline_runs(whole))
    assert len(ids) == 1 and exits == [0]
    files = _offline_runs(cut)
    assert len(files) == 3  # to 4, on to 6, resumed from 4 to 8
    steps, got, cut_ids, cut_exits = _history(files)
    assert len(cut_ids) == 1 and cut_ids != ids
    assert steps == sorted(steps) and len(set(steps)) == len(steps)
    assert cut_exits == [0, 0, 0]
    for tag in ("train/running_mean_return", "episode/return"):
        assert sorted(expected[tag]) == list(range(1, 9))
        assert got[tag] == pytest.approx(expected[tag], rel=1e-6), tag
    assert sorted(expected["eval/return"]) == [4, 8] and sorted(got["eval/return"]) == [4, 6, 8]
    assert got["eval/return"][4] == pytest.approx(expected["eval/return"][4], rel=1e-6)
    assert (cut / "wandb" / "run_id").read_text().strip() == next(iter(cut_ids))
    assert int((cut / "wandb" / "sent_through").read_text()) == 8


def test_the_config_a_video_and_the_final_metrics_reach_the_run(tmp_path):
    from drone_torchrl.training.trainer import train

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["logger=wandb", "algo.episodes=2", *FAST, "eval.video=true"])
    train(cfg, run_dir=tmp_path / "run")
    (path,) = _offline_runs(tmp_path / "run")
    records = list(_records(path))
    (run,) = [r.run for r in records if r.WhichOneof("record_type") == "run"]
    config = {_key(item): json.loads(item.value_json) for item in run.config.update}
    assert config["algo"]["lr"] == 0.0001 and config["env"]["max_steps"] == 30
    assert run.run_group == "adhoc" and run.display_name == "run" and run.project == "drone_torchrl"
    summary = {}
    for r in records:
        if r.WhichOneof("record_type") == "summary":
            summary.update({_key(item): json.loads(item.value_json) for item in r.summary.update})
    assert {"hparam/final_return", "hparam/eval_return"} <= set(summary)
    videos = [
        {_key(item): json.loads(item.value_json) for item in r.history.item}
        for r in records
        if r.WhichOneof("record_type") == "history"
    ]
    videos = [row for row in videos if "eval/video/_type" in row]
    assert len(videos) == 1 and videos[0]["eval/video/_type"] == "video-file" and videos[0]["episodes"] == 2
    gif = path.parent / "files" / videos[0]["eval/video/path"]  # W&B's copy, what it uploads
    assert gif.read_bytes()[:6] == b"GIF89a"
    assert not list((tmp_path / "run" / "wandb").glob("*.gif"))  # the GIF handed to W&B is not kept twice


@pytest.mark.slow
def test_a_two_seed_sweep_in_one_process_gives_two_wandb_runs(tmp_path):
    """``drone-train -m seed=0,1 hydra/launcher=fused logger=wandb``: both agents train in one process,
    each its own W&B run (ids, offline files, steps 1..4), both finished with exit code 0."""
    sweep = tmp_path / "sweep"
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), env.get("PYTHONPATH")]))
    cmd = [sys.executable, "-m", "drone_torchrl.apps.train", "-m", "seed=0,1", "hydra/launcher=fused"]
    cmd += ["logger=wandb", "algo.episodes=4", *FAST, f"hydra.sweep.dir={sweep}"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    jobs = sorted(p.parent for p in sweep.glob("*/.hydra"))
    assert [j.name.rsplit(",", 1)[-1] for j in jobs] == ["seed=0", "seed=1"]
    ids = set()
    for job in jobs:
        (path,) = _offline_runs(job)
        steps, points, run_ids, exits = _history([path])
        assert sorted(points["episode/return"]) == [1, 2, 3, 4] and exits == [0]
        ids |= run_ids
    assert len(ids) == 2


def test_a_failed_run_is_finished_as_failed(tmp_path, monkeypatch):
    """A run that fails closes its W&B run with exit code 1 (W&B shows it as failed), not left open."""
    from drone_torchrl.training import run as run_module
    from drone_torchrl.training.jobs import prepare
    from drone_torchrl.training.trainer import train_jobs

    with initialize_config_dir(config_dir(), version_base="1.3"):
        cfg = compose("config", overrides=["logger=wandb", "algo.episodes=6", *FAST])
    record = run_module.RunRecord.record

    def diverge(self, episodes, metrics):
        record(self, episodes, metrics)
        if self.episodes_done == 3:
            self.fail("training diverged at episode 3: test")

    monkeypatch.setattr(run_module.RunRecord, "record", diverge)
    (outcome,) = train_jobs([prepare(cfg, tmp_path / "run")])
    assert outcome.final is None
    (path,) = _offline_runs(tmp_path / "run")
    _, points, _, exits = _history([path])
    assert exits == [1] and sorted(points["episode/return"]) == [1, 2, 3]


def _wandb_cfg(*overrides: str):
    with initialize_config_dir(config_dir(), version_base="1.3"):
        return compose("config", overrides=["logger=wandb", *overrides])


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        (["logger.mode=cloud"], "logger.mode"),
        (["logger.mode=true"], "logger.mode"),
        (["logger.project=''"], "logger.project"),
        (["logger.project='a/b'"], "logger.project"),
        (["logger.project=null"], "logger.project"),
        (["logger.entity='team:x'"], "logger.entity"),
        (["logger.group='" + "g" * 129 + "'"], "logger.group"),
    ],
)
def test_bad_wandb_values_are_one_line(overrides, names):
    with pytest.raises(ConfigError) as info:
        validate(_wandb_cfg(*overrides))
    message = str(info.value)
    assert "\n" not in message and message.startswith(names), message


def test_a_bad_wandb_mode_variable_is_one_line(monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "")
    with pytest.raises(ConfigError, match=r"^WANDB_MODE='' is not allowed; expected one of"):
        validate(_wandb_cfg())


def test_online_without_credentials_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_API_KEY", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.netrc
    monkeypatch.setenv("NETRC", str(tmp_path / "no-netrc"))
    with pytest.raises(
        ConfigError, match=r"^logger=wandb in online mode needs W&B credentials.*logger.mode=offline"
    ):
        validate(_wandb_cfg("logger.mode=online"))
    validate(_wandb_cfg("logger.mode=offline"))  # offline needs none
