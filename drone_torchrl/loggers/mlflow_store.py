"""``logger=mlflow``: each run is an MLflow run (the ``mlflow`` extra: ``pip install ".[mlflow]"``).

Store: ``logger.tracking_uri``, by default an SQLite file beside the run folders,
``sqlite:///<run folder's parent>/mlflow.db``: one store per sweep (``multirun/<sweep>/mlflow.db``)
and per day for single runs (``outputs/<date>/mlflow.db``). Any MLflow tracking URI works (a
server, ``sqlite:///...``). Experiment: ``logger.experiment``, by default the ``sweep_name``.
Browse with ``mlflow ui --backend-store-uri sqlite:///multirun/lr/mlflow.db`` (the full ``mlflow``
package) or read with :class:`mlflow.tracking.MlflowClient`.

What is logged: every scalar as a metric with its step (a count of episodes done), the flattened
config as params when the run starts, the final metrics as ``hparam/*`` metrics when it ends, and
the run's status (``FINISHED`` when it completes, ``FAILED`` when it fails, ``KILLED`` when a signal
stops it to be continued). Videos are not uploaded: the run folder's
``videos/`` has them. Metrics are buffered and sent in one ``log_batch`` (which MLflow splits into
its largest batches) at every flush; the store's connection is shared by every run of a process, so a population of 1,024 runs
holds one connection, not 1,024 files.

Resume: MLflow is append-only, so a continued run logs into the same MLflow run (its id is kept in
``<run>/<logger.exp_name>/run_id``) and skips the steps that run already has (those logged by the
interrupted process after the checkpoint). REINFORCE's runs retrain those episodes exactly (their
random numbers are a function of the update count), so the skipped values are the ones it would
log; PPO and A2C restart their drones' episodes, so there the values kept are the interrupted
process's. A child run per resume would keep both, but split one run's curves over several MLflow
runs; continuing keeps one curve per run, as the TensorBoard and CSV backends do.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from drone_torchrl.checks import ConfigError
from drone_torchrl.io import run_lock
from drone_torchrl.io.storage import write_atomically
from drone_torchrl.loggers import FAILED, FINISHED, Backend, Logger, RunStatus, flatten_config, register
from drone_torchrl.schema import IF_SET, TensorBoardConf, a_text, store_plugin
from drone_torchrl.sweep_folder import group_name

RUN_ID_FILE = "run_id"
STORE_FILE = "mlflow.db"
# Beside a SQLite store: the lock its first contact takes (<store>.lock).
LOCK_SUFFIX = ".lock"
# MLflow's limit per param value (characters); MlflowClient.log_batch splits a batch into its sizes itself.
MAX_PARAM_CHARS = 6000
# MLflow's run status for how a run ended; any other (stopped, to be continued) is KILLED.
_STATUSES = {FINISHED: "FINISHED", FAILED: "FAILED"}


# MLflow's tracking stores that hold runs, by URI scheme ("" is a folder path: a file store), where
# its registry of stores cannot be read; the registry's others ("uc", "databricks-uc") hold models only.
KNOWN_SCHEMES = ("", "databricks", "file", "http", "https", "mssql", "mysql", "postgresql", "sqlite")
MODEL_ONLY_SCHEMES = ("uc", "databricks-uc")


def _sqlite_file(tracking_uri: str) -> Path | None:
    """The database file of a ``sqlite:///<path>`` URI (None for another store or in-memory SQLite)."""
    prefix = "sqlite:///"
    path = tracking_uri[len(prefix) :] if tracking_uri.startswith(prefix) else ""
    return Path(path) if path and path != ":memory:" else None


class MLflowLogger(Logger):
    """One drone_torchrl run as one MLflow run, buffered (videos are not uploaded); the backend's ``make``.

    The store is ``logger.tracking_uri`` (default: ``mlflow.db`` beside the run folder), the
    experiment ``logger.experiment`` (default: the sweep's name; created if missing), the MLflow
    run's name the run folder's, its id kept in ``<run_dir>/<logger.exp_name>/run_id``. The
    flattened config is logged as params when the logger starts (those a continued run has are
    skipped). ``resumed_at``: on resume, the steps the store has already are skipped.
    """

    def __init__(self, cfg: DictConfig, run_dir: Path, resumed_at: int | None) -> None:
        from mlflow.entities import Param
        from mlflow.tracking import MlflowClient  # installed: check_backend refused the config otherwise

        # MLflow's store announces creating and migrating its tables at INFO level, once per process.
        for name in ("mlflow.store.db.utils", "alembic"):
            logging.getLogger(name).setLevel(logging.WARNING)
        run_dir = Path(run_dir)
        uri = cfg.logger.tracking_uri or f"sqlite:///{(run_dir.resolve().parent / STORE_FILE)}"
        id_file = run_dir / cfg.logger.exp_name / RUN_ID_FILE
        self.scalars: list[tuple[str, float, int]] = []
        self._skip_to = -1  # steps <= this are in the store already
        # Processes that open one SQLite store take turns: the first to reach a new store creates its
        # tables (MLflow's migrations; two at once collide, ``duplicate column name: step``, and the
        # second run was lost), and an experiment is created once. Other stores serialise themselves
        # (a server), or are one process's (a folder).
        db = _sqlite_file(uri)
        lock = (
            contextlib.nullcontext()
            if db is None
            else run_lock.exclusive(db.with_name(db.name + LOCK_SUFFIX))
        )
        with lock:  # MlflowClient opens the store, creating its tables
            self.client = client = MlflowClient(tracking_uri=uri)
            if id_file.is_file():
                self.run_id = id_file.read_text().strip()
                if resumed_at is not None:
                    keys = client.get_run(self.run_id).data.metrics
                    steps = [m.step for key in keys for m in client.get_metric_history(self.run_id, key)]
                    self._skip_to = max(steps, default=-1)
                client.update_run(self.run_id, status="RUNNING")
            else:
                experiment = cfg.logger.experiment or group_name(cfg.sweep_name, run_dir)
                found = client.get_experiment_by_name(experiment)
                experiment_id = found.experiment_id if found else client.create_experiment(experiment)
                tags = {"run_dir": str(run_dir)}
                self.run_id = client.create_run(experiment_id, run_name=run_dir.name, tags=tags).info.run_id
        if not id_file.is_file():
            write_atomically(id_file, f"{self.run_id}\n".encode())
        have = client.get_run(self.run_id).data.params
        params = [
            Param(key, str(value)[:MAX_PARAM_CHARS])
            for key, value in flatten_config(cfg).items()
            if key not in have  # params cannot change in MLflow; a continued run has them already
        ]
        client.log_batch(self.run_id, params=params)

    def log_final_hparams(self, cfg: DictConfig | dict, metrics: dict[str, float]) -> None:
        # MLflow shows params and metrics side by side already; the final metrics under hparam/*,
        # as TensorBoard's HPARAMS tab names them. Step 0, as there.
        """Log the final ``metrics`` as ``hparam/*`` metrics at step 0."""
        self.log_metrics({f"hparam/{k}": v for k, v in metrics.items()}, step=0)

    def flush(self) -> None:
        """Send the buffered metrics to the store in one batch."""
        from mlflow.entities import Metric

        if not self.scalars:
            return
        now = int(time.time() * 1000)
        metrics = [
            Metric(tag, float(value), now, int(step))
            for tag, value, step in self.scalars
            if int(step) > self._skip_to or tag.startswith("hparam/")
        ]
        self.scalars.clear()
        self.client.log_batch(self.run_id, metrics=metrics)

    def close(self, status: RunStatus) -> None:
        """Flush, then mark the MLflow run finished, failed or killed by ``status``."""
        self.flush()
        # A run stopped by a signal is continued later (update_run sets RUNNING again).
        self.client.set_terminated(self.run_id, status=_STATUSES.get(status, "KILLED"))


def validate(cfg: Mapping[str, Any]) -> None:
    """Check ``logger.tracking_uri``: a store MLflow can open, and a SQLite file's folder exists.

    An unknown scheme was a traceback when the run started; SQLite creates the file, not the folder.
    """
    uri = cfg.logger.tracking_uri
    if uri is None:
        return
    from mlflow.utils.uri import get_uri_scheme

    try:  # the stores this MLflow can open, plug-ins included
        from mlflow.tracking._tracking_service.utils import _tracking_store_registry

        schemes = set(_tracking_store_registry._registry)
    except (ImportError, AttributeError):  # a private name: another MLflow version may move it
        schemes = set(KNOWN_SCHEMES)
    schemes = sorted(schemes - set(MODEL_ONLY_SCHEMES))
    try:
        scheme = get_uri_scheme(uri)
    except Exception:  # noqa: BLE001  (MLflow refuses e.g. an unknown database engine, sqlitex://)
        scheme = None
    if scheme not in schemes:
        listed = ", ".join(f"{s}://" for s in schemes if s)
        raise ConfigError.of("logger.tracking_uri", uri, f"a folder path or a URI of {listed}")
    path = _sqlite_file(uri)
    if path is not None and not path.expanduser().parent.is_dir():
        raise ConfigError.of(
            "logger.tracking_uri", uri, f"a SQLite file in a folder that exists ({path.parent} does not)"
        )


@dataclass
class MLflowConf(TensorBoardConf):
    """``logger.*`` of ``logger.backend=mlflow``."""

    tracking_uri: Any = a_text(optional=True, on_resume=IF_SET)
    experiment: Any = a_text(optional=True, on_resume=IF_SET)


store_plugin("logger", "mlflow", MLflowConf)

register(
    Backend(
        "mlflow",
        MLflowLogger,
        resume_rule="continues the same MLflow run and skips the steps it already has (append-only store)",
        summary="an MLflow run per run in a tracking store (SQLite beside the runs by default)",
        validate=validate,
        extra="mlflow",
    )
)
