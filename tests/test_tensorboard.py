"""TensorBoard, served and read: what a user sees in the dashboard after a sweep.

Starts ``tensorboard --logdir <sweep>`` on 127.0.0.1 and reads its HTTP data API (the one the
dashboard itself calls): every run listed, the scalars of docs/training.md's TensorBoard table with points, the HPARAMS plugin
with the sweep's hyper-parameters and final metrics, and the evaluation video as images.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from drone_torchrl.training.jobs import sweep_jobs

# The TensorBoard table of docs/training.md (one point per episode, update or evaluation).
SCALARS = (
    "episode/return",
    "episode/length",
    "episode/time_in_zone",
    "episode/negative_thrust_fraction",
    "train/loss",
    "train/grad_norm",
    "train/running_mean_return",
    "train/running_mean_length",
    "policy/std_mean",
    "eval/return",
    "eval/length",
    "eval/time_in_zone",
)
GRID = ("algo.lr=1e-3,1e-4", "seed=0")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _get(url: str, body: dict | None = None):
    data = None if body is None else json.dumps(body).encode()
    headers = {"Content-Type": "application/json", "X-TensorBoard-Feature-Flags": "{}"}
    with urllib.request.urlopen(urllib.request.Request(url, data=data, headers=headers), timeout=30) as r:
        return json.loads(r.read())


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("tb")
    sweep = root / "sweep"
    subprocess.run(
        [
            sys.executable, "-m", "drone_torchrl.apps.train", "-m", *GRID, "hydra/launcher=fused",
            f"hydra.sweep.dir={sweep}", "algo.episodes=4", "env.max_steps=30", "eval.every_episodes=2",
            "eval.episodes=1", "progress=false", "logger.flush_every_s=0",
        ],
        check=True, capture_output=True, text=True, timeout=300, cwd=root,
    )  # fmt: skip
    port = _free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "tensorboard.main", "--logdir", str(sweep), "--host", "127.0.0.1",
         "--port", str(port), "--reload_interval", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 90
        while True:  # until the server answers and has loaded every run's scalars
            try:
                tags = _get(f"{base}/data/plugin/scalars/tags")
                if len(tags) >= 2 and all("eval/return" in t for t in tags.values()):
                    break
            except OSError:
                pass
            if time.monotonic() > deadline or server.poll() is not None:
                pytest.fail("tensorboard did not start or did not load the runs within 90 s")
            time.sleep(0.5)
        yield base, sweep
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_every_run_is_listed(served):
    base, sweep = served
    runs = set(_get(f"{base}/data/runs"))
    expected = {str((job / "tensorboard").relative_to(sweep)) for job in sweep_jobs(sweep)}
    assert len(expected) == 2 and expected <= runs, (expected, runs)


def test_the_readme_scalars_have_points(served):
    base, _ = served
    tags = _get(f"{base}/data/plugin/scalars/tags")
    for run, run_tags in tags.items():
        assert set(SCALARS) <= set(run_tags), (run, sorted(set(SCALARS) - set(run_tags)))
        points = _get(
            f"{base}/data/plugin/scalars/scalars?run={urllib.request.quote(run)}&tag=episode/return"
        )
        assert [p[1] for p in points] == [1, 2, 3, 4]  # one per episode, x = episodes done
        evals = _get(f"{base}/data/plugin/scalars/scalars?run={urllib.request.quote(run)}&tag=eval/return")
        assert [p[1] for p in evals] == [2, 4]  # every 2 episodes; the last is the final one


def test_hparams_lists_the_swept_values_with_final_metrics(served):
    base, _ = served
    experiment = _get(f"{base}/data/plugin/hparams/experiment", {"experimentName": ""})
    names = {h["name"] for h in experiment["hparamInfos"]}
    assert {"algo.lr", "algo.gamma", "seed", "model.distribution"} <= names
    metrics = {m["name"]["tag"] for m in experiment["metricInfos"]}
    assert {"hparam/final_return", "hparam/eval_return"} <= metrics, metrics
    sessions = _get(
        f"{base}/data/plugin/hparams/session_groups",
        {"experimentName": "", "allowedStatuses": ["STATUS_UNKNOWN", "STATUS_SUCCESS"], "colParams": [],
         "startIndex": 0, "sliceSize": 100},
    )  # fmt: skip
    found = {
        next(v for k, v in g["hparams"].items() if k == "algo.lr"): {
            m["name"]["tag"] for m in g["metricValues"]
        }
        for g in sessions["sessionGroups"]
    }
    assert sorted(found) == [0.0001, 0.001] and all("hparam/final_return" in m for m in found.values()), found


def test_the_evaluation_video_is_there(served):
    base, _ = served
    tags = _get(f"{base}/data/plugin/images/tags")
    assert len(tags) == 2 and all("eval/video" in t for t in tags.values()), tags
    run = next(iter(tags))
    images = _get(f"{base}/data/plugin/images/images?run={urllib.request.quote(run)}&tag=eval/video")
    assert [i["step"] for i in images] == [2, 4]
    with urllib.request.urlopen(
        f"{base}/data/plugin/images/individualImage?{images[-1]['query']}", timeout=30
    ) as r:
        assert r.read(6) in (b"GIF89a", b"GIF87a")  # TensorBoard's animated video frames


@pytest.mark.parametrize(
    ("step", "scalars"),
    [
        (0, [("a", 0.0)]),
        (7, [("episode/return", 123.456), ("train/loss", -1e-3), ("episode/termination_cause/FLOOR", 3)]),
        (10**12, [("big", 1e39), ("small", -1e39), ("inf", float("inf"))]),
        (300, [("t" * 200, 2.5), ("é/ü", -0.0)]),
    ],
)
def test_hand_encoded_scalar_events_decode_as_tensorboards_own(step, scalars):
    """The logger's scalar events decode to the Event tensorboard's protobuf classes build."""
    from tensorboard.compat.proto import event_pb2, summary_pb2

    from drone_torchrl.loggers.tb_logger import scalar_event, scalar_value

    ours = event_pb2.Event.FromString(scalar_event(1.7e9, step, [scalar_value(t, v) for t, v in scalars]))
    values = [summary_pb2.Summary.Value(tag=t, simple_value=v) for t, v in scalars]
    assert ours == event_pb2.Event(wall_time=1.7e9, step=step, summary=summary_pb2.Summary(value=values))
    assert [v.tag for v in ours.summary.value] == [t for t, _ in scalars]
