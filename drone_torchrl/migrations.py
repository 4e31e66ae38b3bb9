"""Settings earlier versions had, and what each means now.

The one place saved configs, checkpoints and command lines are read through.

Until ``backend`` existed, three keys picked an implementation: ``engine`` (``fused`` or ``torchrl``),
``compile`` (the fused engine's C++ kernels or ``torch.compile``, else eager PyTorch) and PPO/A2C's
``algo.collector`` (``fused`` or ``torchrl``); ``steps_per_call`` and ``updates_per_call`` tuned
the fused engine's PyTorch path and its calls. ``backend`` replaces them: ``fast`` (the C++ engine)
where ``engine=fused`` or ``algo.collector=fused`` ran, ``reference`` (TorchRL) where ``torchrl``
did. ``compile``, ``steps_per_call`` and ``updates_per_call`` pick nothing any more (the fast engine
is compiled C++, flies whole episodes per call, and the loop calls it as often as nothing falls
due), so they are dropped.

Keys every run had one value of left the config (:data:`FIXED`): ``metrics.running_mean_window``
(the paper's 100, now :data:`drone_torchrl.episodes.RUNNING_MEAN_WINDOW`) and ``logger.video_fps``
(50, the env's ``1 / env.dt``, from which videos now take their rate). A saved config or a command
line with that value reads as today's; another value is refused in one line: the run would not be
what it was.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from drone_torchrl.checks import ConfigError

FAST, REFERENCE = "fast", "reference"
BACKENDS = (REFERENCE, FAST)
# What an engine or on-policy collector name meant, as a backend.
_AS_BACKEND = {"fused": FAST, "torchrl": REFERENCE}
# The keys that picked an implementation, and the one that picks it now.
REPLACED = ("engine", "algo.collector")
DROPPED = ("compile", "steps_per_call", "updates_per_call")
#: Keys removed from the config, each with the one value every run had and what took its place.
FIXED: dict[str, tuple[Any, str]] = {
    "metrics.running_mean_window": (100, "the paper's window, drone_torchrl.episodes.RUNNING_MEAN_WINDOW"),
    "logger.video_fps": (50, "videos play in real time, 1 / env.dt frames a second"),
}


def _is_fixed_value(key: str, value: Any) -> bool:
    """Whether ``value`` (a config's, or a command line's text) is the one value :data:`FIXED` ``key`` had."""
    try:
        return not isinstance(value, bool) and float(value) == FIXED[key][0]
    except (TypeError, ValueError):
        return False


def fixed_refusal(key: str, value: Any) -> str:
    """The one line refusing ``key=value`` of a key :data:`FIXED` removed."""
    fixed, replaced = FIXED[key]
    return (
        f"{key}={value} is not allowed: the key was removed and every run uses {fixed} ({replaced}); drop it"
    )


def _pop(config: dict[str, Any], key: str) -> Any:
    """Remove ``section.key`` from nested dicts (and the section, if it leaves it empty); its value, or None."""
    section, leaf = key.split(".")
    node = config.get(section)
    if not isinstance(node, Mapping):
        return None
    config[section] = node = dict(node)  # a copy: the caller's config is left as it is
    value = node.pop(leaf, None)
    if not node:
        del config[section]
    return value


def backend_of(engine: Any = None, collector: Any = None) -> str:
    """The backend an old run trained with.

    Its on-policy ``algo.collector`` if it had one (PPO and A2C's batches), else its ``engine``; a
    config saved before ``engine`` existed ran TorchRL's loop (``reference``).
    """
    return _AS_BACKEND.get(engine if collector is None else collector, REFERENCE)


def migrate_config(config: Mapping[str, Any]) -> dict[str, Any]:
    """A saved config (plain nested dicts) in today's keys.

    ``backend`` from ``engine`` and ``algo.collector``, the dropped keys removed, the :data:`FIXED`
    ones too where they hold the value every run had (another raises
    :class:`~drone_torchrl.checks.ConfigError`). A config that has ``backend`` keeps it.
    """
    out = dict(config)
    for key in FIXED:
        value = _pop(out, key)
        if value is not None and not _is_fixed_value(key, value):
            raise ConfigError(
                f"a saved config's {fixed_refusal(key, value)}: it cannot be continued as it was trained"
            )
    collector, engine = _pop(out, "algo.collector"), out.pop("engine", None)
    for key in DROPPED:
        out.pop(key, None)
    out.setdefault("backend", backend_of(engine, collector))
    return out


# Old keys typed on the command line are passed to Hydra as ``+legacy.<key>=<value>``: Hydra composes
# them (the keys themselves are gone from the config), the job folder keeps the name the old key
# gave it (:func:`job_dirname`), and :func:`apply_legacy` turns them into today's keys before any check.
LEGACY = "legacy"
_PREFIX = f"+{LEGACY}."


def legacy_arguments(args: list[str]) -> tuple[list[str], list[str]]:
    """The command line with old-key overrides passed as ``+legacy.key=value``, and notes to print.

    Each old-key override is ``key=value``; each note is one line, what the key is now. A value the
    old key never took, or a command line that sets both an old key and ``backend`` (which one
    would win is not obvious), raises :class:`~drone_torchrl.checks.ConfigError`.
    """
    out, notes, replaced = [], [], []
    for arg in args:
        key, sep, value = arg.partition("=")
        if arg.startswith("-") or not sep or not is_old_key(key):
            out.append(arg)
            continue
        if key in REPLACED:
            backend = _AS_BACKEND.get(value.strip())
            if backend is None:
                choices = " or ".join(f"{old} (backend={new})" for old, new in _AS_BACKEND.items())
                raise ConfigError(f"{key}={value!r} is not allowed; expected {choices}")
            notes.append(
                f"note: {key}={value} is now backend={backend} (the key that picks the implementation)"
            )
            replaced.append(key)
        elif key in DROPPED:
            notes.append(
                f"note: {key}={value} is ignored: it tuned the fused engine's PyTorch path, which backend=fast "
                "(compiled C++, whole episodes per call) replaced"
            )
        elif not _is_fixed_value(key, value):
            raise ConfigError(fixed_refusal(key, value))
        else:
            notes.append(
                f"note: {key}={value} is ignored: the key was removed, every run uses it ({FIXED[key][1]})"
            )
        out.append(f"{_PREFIX}{arg}")
    if replaced and any(a.partition("=")[0].lstrip("+") == "backend" for a in args):
        raise ConfigError(
            f"{replaced[0]}= and backend= are both given: backend replaced {replaced[0]}; drop {replaced[0]}="
        )
    return out, notes


def apply_legacy(cfg: Any) -> None:
    """Turn a composed config's ``legacy`` node (old keys) into today's keys, in place.

    The old keys come from the command line: ``engine``/``algo.collector`` set ``backend``, the
    dropped keys go; the node is removed.
    """
    from omegaconf import OmegaConf, open_dict

    if cfg.get(LEGACY) is None:
        return
    engine = OmegaConf.select(cfg, f"{LEGACY}.engine")
    collector = OmegaConf.select(cfg, f"{LEGACY}.algo.collector")
    with open_dict(cfg):
        if engine is not None or collector is not None:
            cfg.backend = backend_of(engine, collector)
        del cfg[LEGACY]


def job_dirname(override_dirname: str) -> str:
    """A sweep job's folder name, with old keys named as they were typed.

    It is Hydra's ``override_dirname`` with an old key as ``compile=True``, not
    ``+legacy.compile=True``, so a sweep started before ``backend`` existed finds its job folders
    when its command is run again.
    """
    if _PREFIX not in override_dirname:
        return override_dirname
    items, depth, start = [], 0, 0
    for i, char in enumerate(override_dirname):  # split at the commas between overrides, not in lists
        depth += (char in "[{(") - (char in "]})")
        if char == "," and depth == 0:
            items.append(override_dirname[start:i])
            start = i + 1
    items.append(override_dirname[start:])
    return ",".join(sorted(item.removeprefix(_PREFIX) for item in items))


def is_old_key(key: str) -> bool:
    """Whether ``key`` is an old key :func:`legacy_arguments` reads on a command line."""
    return key in REPLACED or key in DROPPED or key in FIXED
