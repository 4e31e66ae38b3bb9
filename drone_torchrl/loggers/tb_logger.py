"""``logger=tensorboard`` (the default backend): buffered scalars, written in batches, no writer held open.

The files go to ``<run>/<logger.exp_name>``.

TorchRL's ``TensorboardLogger`` keeps a ``SummaryWriter`` (an open event file and a writer thread)
for the life of a run and sends every scalar through the thread's queue, one by one. A
population of a thousand runs cannot hold a thousand writers, and at that rate its logging would
cost more than its training. :class:`RunLogger` buffers the scalars (``log_scalars``,
``log_metrics``), and :meth:`RunLogger.flush` appends them to the run's event file
as TensorBoard records (tensorboard's own ``Event`` protos, one per step holding all of that step's
scalars, as ``tf.summary.merge_all`` writes them; no thread), opening the file only for that. The
records' CRC32C checksums come from ``google-crc32c`` (C): tensorboard's ``RecordWriter`` computes
them in pure Python when TensorFlow is absent, which was most of the logging time of a population. Videos and the final hparams, a few per run, are
tensorboard's ``Summary`` protos in the same file. TensorBoard reads the event files in
``<run>/<exp_name>`` as one run.

Steps count episodes done (see :func:`~drone_torchrl.loggers.log_update`). On resume, the first flush passes
``purge_step``, one past the checkpoint's count: TensorBoard then drops the events the interrupted
process logged after the checkpoint, so the curves do not fold back on themselves, and keeps the
checkpoint's own last update and evaluation.

Measured against ``SummaryWriter`` and TorchRL's ``TensorboardLogger`` (``benchmarks/loggers.py``,
figures in docs/benchmarks.md: the same scalars at the same steps read back from all three), it
writes a scalar 45 to 95 times faster; that matters for a single run and a fused sweep, where
either of the others would add a tenth to a fifth to a default ``drone-train``'s time, and is why
it is kept; a population's summaries (six scalars an update for all its agents: at 1,024 agents under
two thousandths of its training either way) would not need it.
"""

from __future__ import annotations

import functools
import math
import os
import socket
import struct
import time
from pathlib import Path

import google_crc32c
import numpy as np
from omegaconf import DictConfig

from drone_torchrl.io.storage import writing
from drone_torchrl.io.video import gif_bytes
from drone_torchrl.loggers import Backend, Logger, flatten_config, register
from drone_torchrl.schema import TensorBoardConf, store_plugin

# TFRecord framing (what tensorboard's RecordWriter writes): a masked CRC32C of the length and of the data.
_CRC_MASK_DELTA = 0xA282EAD8


def _masked_crc(data: bytes) -> bytes:
    crc = google_crc32c.value(data)
    return struct.pack("<I", (((crc >> 15) | (crc << 17)) + _CRC_MASK_DELTA) & 0xFFFFFFFF)


def tf_record(data: bytes) -> bytes:
    """One TFRecord: ``length, crc(length), data, crc(data)`` (little-endian), as TensorBoard reads it."""
    header = struct.pack("<Q", len(data))
    return header + _masked_crc(header) + data + _masked_crc(data)


# Scalar events are encoded here rather than through the protobuf classes: building a ``Value``
# message per scalar and an ``Event`` per step in Python, at a thousand
# runs logging a dozen scalars an update was as much as the update itself. The wire format of the
# two messages involved is small and fixed (tensorboard's event.proto and summary.proto):
#   Event   { double wall_time = 1; int64 step = 2; Summary summary = 5; }
#   Summary { repeated Value value = 1; }    Value { string tag = 1; float simple_value = 2; }
# tests/test_tensorboard.py checks the bytes decode to the Event tensorboard's own classes build.
_FLOAT = struct.Struct("<f")


def _varint(n: int) -> bytes:
    n &= (1 << 64) - 1  # int64 fields: a negative number as its two's complement
    out = bytearray()
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _length_delimited(field_key: bytes, payload: bytes) -> bytes:
    return field_key + _varint(len(payload)) + payload


@functools.cache
def _value_head(tag: str) -> bytes:
    """The entry's key, length and tag field: the same for every value of ``tag``."""
    inner = _length_delimited(b"\x0a", tag.encode()) + b"\x15"
    return b"\x0a" + _varint(len(inner) + _FLOAT.size) + inner


def scalar_value(tag: str, value: float) -> bytes:
    """One ``Summary.value`` entry (field 1 of ``Summary``) holding ``simple_value`` for ``tag``."""
    head, value = _value_head(tag), float(value)
    try:
        return head + _FLOAT.pack(value)
    except OverflowError:  # beyond float32: infinity, as protobuf stores it
        return head + _FLOAT.pack(math.copysign(math.inf, value))


def scalar_event(wall_time: float, step: int, values: list[bytes]) -> bytes:
    """A serialised ``Event`` at ``step`` whose summary holds ``values`` (from :func:`scalar_value`)."""
    return (
        b"\x09"
        + struct.pack("<d", wall_time)
        + b"\x10"
        + _varint(step)
        + _length_delimited(b"\x2a", b"".join(values))
    )


class RunLogger(Logger):
    """Buffered TensorBoard logging into ``<log_dir>/<exp_name>``.

    Args:
        exp_name: the subfolder of ``log_dir`` the event file goes in.
        log_dir: the run folder.
        purge_step: on resume, one past the checkpoint's count: TensorBoard drops the events the
            interrupted process logged after the checkpoint (None: a new run).
    """

    def __init__(self, exp_name: str, log_dir: str | Path, purge_step: int | None = None) -> None:
        self.log_dir = Path(log_dir) / exp_name
        self._purge_step = purge_step
        self.scalars: list[tuple[str, float, int]] = []
        self._summaries: list = []  # (step, a ready-made Summary proto): videos, hparams
        self._events: Path | None = None

    def flush(self) -> None:
        """Append the buffered scalars to this logger's event file (opened only for this)."""
        if not (self.scalars or self._summaries):
            return
        from tensorboard.compat.proto import event_pb2

        records = []
        now = time.time()
        if self._events is None:
            with writing(self.log_dir):
                self.log_dir.mkdir(parents=True, exist_ok=True)
            # TensorBoard reads a run's event files in name order, and a resumed run's purge only
            # works if its file comes after the interrupted one's: the name starts with the time in
            # nanoseconds (whole seconds, as SummaryWriter names them, tie within a second).
            self._events = self.log_dir / (
                f"events.out.tfevents.{time.time_ns()}.{socket.gethostname()}.{os.getpid()}.{id(self)}"
            )
            records.append(event_pb2.Event(wall_time=now, file_version="brain.Event:2"))
            if self._purge_step is not None:  # what SummaryWriter(purge_step=...) writes
                start = event_pb2.SessionLog(status=event_pb2.SessionLog.START)
                records.append(event_pb2.Event(wall_time=now, step=self._purge_step, session_log=start))
                self._purge_step = None
        records.extend(
            event_pb2.Event(wall_time=now, step=step, summary=summary) for step, summary in self._summaries
        )
        steps: dict[int, list[bytes]] = {}
        for name, value, step in self.scalars:
            steps.setdefault(int(step), []).append(scalar_value(name, value))
        data = [record.SerializeToString() for record in records]
        data.extend(scalar_event(now, step, values) for step, values in steps.items())
        with writing(self._events), self._events.open("ab") as f:
            f.write(b"".join(tf_record(d) for d in data))
        self.scalars.clear()
        self._summaries.clear()

    def log_frames(self, name: str, frames: np.ndarray, step: int, fps: float) -> None:
        """Log ``[T, H, W, 3]`` uint8 frames as a TensorBoard video (an animated GIF image summary).

        It is the record ``SummaryWriter.add_video`` writes, with the GIF from
        :func:`~drone_torchrl.io.video.gif_bytes`: add_video's moviepy took about ten times as long
        for a training video.
        """
        from tensorboard.compat.proto.summary_pb2 import Summary

        _, height, width, channels = frames.shape
        image = Summary.Image(
            height=height, width=width, colorspace=channels, encoded_image_string=gif_bytes(frames, fps)
        )
        self._summaries.append((step, Summary(value=[Summary.Value(tag=name, image=image)])))
        self.flush()

    def log_final_hparams(self, cfg: DictConfig | dict, metrics: dict[str, float]) -> None:
        """Flattened config + final metrics, so TensorBoard's HPARAMS tab compares the runs of a sweep.

        The same records ``SummaryWriter.add_hparams(..., run_name=".")`` writes, into this run's file.
        """
        from torch.utils.tensorboard.summary import hparams

        final = {f"hparam/{k}": v for k, v in metrics.items()}
        self._summaries.extend((0, summary) for summary in hparams(flatten_config(cfg), final))
        self.log_metrics(final, step=0)
        self.flush()


def make(cfg: DictConfig, run_dir: Path, resumed_at: int | None) -> RunLogger:
    """The TensorBoard logger of the run in ``run_dir`` (``resumed_at``: the count it resumes from)."""
    # The checkpoint's own last update and evaluation were logged at its count: TensorBoard drops
    # events from count + 1 on, those the interrupted process logged after the checkpoint.
    purge = None if resumed_at is None else resumed_at + 1
    return RunLogger(cfg.logger.exp_name, run_dir, purge_step=purge)


# Its keys are the ones every backend has: drone_torchrl.schema.TensorBoardConf.
store_plugin("logger", "tensorboard", TensorBoardConf)

register(
    Backend(
        "tensorboard",
        make,
        resume_rule="events logged after the checkpoint are dropped (TensorBoard's purge_step), the rest kept",
        summary="TensorBoard event files in `<run>/tensorboard/`: scalars, evaluation videos, hparams (the default)",
    )
)
