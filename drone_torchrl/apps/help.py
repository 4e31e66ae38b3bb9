"""The ``--help`` page of ``drone-train``, ``drone-eval`` and ``drone-export``, made from ``conf/``.

The page lists the config groups with their options and every key of the composed config with its
value and a one-line meaning. It is composed by Hydra as the command would compose it (defaults
lists, packages, ``_self_``, the experiment presets, the command line's overrides), in well under a
second and without importing torch:

- The schemas (:mod:`drone_torchrl.schema` and each plug-in's) live in modules that import torch, so
  each schema a ``conf/`` defaults list names (``/schema_config@_here_``) is stood in for by an empty
  config, but for the env's physics and arena (:class:`~drone_torchrl.envs.params.DroneParams`, torch-free,
  their one home: defaults and meanings). The YAML files set every other key (the schema holds no
  values; it refuses what they lack), so the keys and values are those of the real composition; a
  value is checked when the command runs.
- The meanings are the YAML files' own comments, their one home: a key's comment on its line, else
  the comment block right above it (up to its first full stop); a key the chosen option leaves
  uncommented takes the same key's comment in another option of its group (``algo.lr``). PyYAML and OmegaConf drop comments,
  and ruamel.yaml is not a dependency, so :func:`key_comments` reads them with a small line parser
  over the simple block-style YAML ``conf/`` is written in (one key per line; lists in flow style or
  as ``- item`` lines).
"""

from __future__ import annotations

import re
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

from drone_torchrl.envs.params import PARAM, DroneParams

# The root-level configs a conf/ defaults list names: the schemas (``- /schema_config@_here_``).
_ROOT_ENTRY = re.compile(r"^\s*-\s*/(\w+)@", re.MULTILINE)
# The schemas with an env node, whose physics and arena keys (DroneParams') no conf/ file sets.
_ENV_SCHEMAS = ("schema_config", "schema_eval")
# ``key: value  # comment`` (a key is a plain word; conf/ quotes no keys).
_KEY_LINE = re.compile(r"^(?P<indent>\s*)(?P<key>[A-Za-z_][\w-]*):(?:\s+(?P<rest>.*))?$")
# A comment after a value: `` #`` outside quotes (conf/'s quoted values hold no ``#``).
_INLINE_COMMENT = re.compile(r"\s#\s?(?P<comment>.*)$")
# Hydra's flags that choose another config than the command's: its own help then applies.
_OTHER_CONFIG = ("--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd")


# Each command's primary config (conf/<config>.yaml), and the groups its defaults list does not
# choose that it takes all the same (+sweep=lr, hydra/launcher=population).
APPS = {
    "drone-train": ("config", ("sweep", "hydra/launcher")),
    "drone-eval": ("eval", ()),
    "drone-export": ("export", ()),
}


def conf_folder() -> Path:
    """The ``conf/`` folder: ``drone_torchrl/conf`` in a wheel, the top-level one in a checkout."""
    package = Path(__file__).resolve().parent.parent
    for candidate in (package / "conf", package.parent / "conf"):
        if (candidate / "config.yaml").is_file():
            return candidate
    raise FileNotFoundError(f"drone_torchrl's conf/ folder is missing (looked in {package} and its parent)")


def answer_help(prog: str, args: Sequence[str] | None = None) -> None:
    """Print ``prog``'s page and exit 0 if ``args`` (the command line's if None) ask for it.

    They ask with ``--help`` or ``-h``, unless they choose another config (Hydra's own help then
    applies). A command line Hydra cannot compose exits 1 with one line on stderr.
    """
    from drone_torchrl.compat import hydra_args_parser

    args = sys.argv[1:] if args is None else list(args)
    if not any(a in ("--help", "-h") for a in args) or any(a.split("=", 1)[0] in _OTHER_CONFIG for a in args):
        return
    print(page(prog, hydra_args_parser().parse_known_args(args)[0].overrides))
    sys.exit(0)


def page(prog: str, overrides: Sequence[str] = ()) -> str:
    """The ``--help`` page of ``prog`` (``drone-train``...), its config composed with ``overrides``.

    Overrides Hydra cannot compose exit 1 with its message in one line.
    """
    config, extra_groups = APPS[prog]
    conf = conf_folder()
    groups, keys = compose(conf, config, overrides, extra_groups, prog)
    lines = [
        f"{prog}: {_summary(conf / f'{config}.yaml')}",
        "",
        f"Usage: {prog} [GROUP=OPTION ...] [KEY=VALUE ...]",
        f"       {prog} --cfg job [...]   print the composed config and exit",
        f"       {prog} --hydra-help      Hydra's own flags (-m, --config-dir, ...)",
    ]
    if groups:  # drone-export has none
        lines += [
            "",
            f"Config groups (GROUP=OPTION; * marks the option chosen, a + is needed for groups {prog} "
            "does not choose by default):",
        ]
    for group, options, chosen in groups:
        marked = " | ".join(f"{o}*" if o == chosen else o for o in options)
        lines.append(f"  {group if chosen is not None else '+' + group}: {marked}")
        for option in options:
            summary = _summary(conf / group / f"{option}.yaml", rf"\+?{re.escape(group)}={re.escape(option)}")
            if summary:
                lines.append(f"      {option:<{max(map(len, options))}}  {summary}")
    lines += ["", f"Keys (KEY=VALUE), with their values in conf/{config}.yaml as composed:"]
    width = max(len(key) + len(value) for key, value, _ in keys) + 3
    for key, value, meaning in keys:
        lines.append(f"  {f'{key}={value}':<{width}}  {meaning}".rstrip())
    lines += ["", "Meanings are the comments of conf/'s YAML files; docs/training.md has the full story."]
    return "\n".join(lines)


def compose(
    conf: Path, config: str, overrides: Sequence[str], extra_groups: Sequence[str], prog: str
) -> tuple[list[tuple[str, list[str], str | None]], list[tuple[str, str, str]]]:
    """Compose ``conf/<config>.yaml`` with Hydra, the schemas stood in for (see the module's docstring).

    Returns the groups, each as ``(group, options, chosen)`` (``chosen`` is None for a group of
    ``extra_groups`` the defaults list does not choose), and ``(key, value, meaning)`` of every key,
    in the config's order. Overrides that do not compose exit 1 with one line naming ``prog``.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.config_store import ConfigStore
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from hydra.types import RunMode
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    # hydra/launcher=fused and hydra/sweeper=population, which the configs name (no torch).
    import drone_torchrl.launcher_schemas  # noqa: F401

    store = ConfigStore.instance()
    named = {name for path in conf.rglob("*.yaml") for name in _ROOT_ENTRY.findall(path.read_text("utf-8"))}
    # The real schema, where a process has imported it, stays.
    for name in sorted(named - {n.removesuffix(".yaml") for n in store.list("")}):
        node = {"env": asdict(DroneParams())} if name in _ENV_SCHEMAS else {}
        store.store(name=name, node=node, provider="drone_torchrl.apps.help")
    try:
        with initialize_config_dir(str(conf), version_base="1.3", job_name=config):
            cfg = hydra_compose(config, overrides=list(overrides), return_hydra_config=True)
            loader = GlobalHydra.instance().hydra.config_loader  # type: ignore[union-attr]
            choices = dict(cfg.hydra.runtime.choices)
            defaults = loader.compute_defaults_list(config, list(overrides), RunMode.RUN).defaults
            # The groups the defaults list chooses, in its order (conf/<group>/<option>), then the app's others.
            names = [d.config_path.rpartition("/")[0] for d in defaults if d.config_path]
            names = [g for g in dict.fromkeys(names) if g in choices and "/" not in g] + list(extra_groups)
            groups = [(g, sorted(loader.get_group_options(g)), choices.get(g)) for g in names]
    except (HydraException, OmegaConfBaseException) as err:
        sys.exit(f"{prog}: error: {_one_line(str(err))}")
    # The env's physics and arena: DroneParams' meanings, unless a chosen option's comment says more.
    meanings = {f"env.{f.name}": f.metadata[PARAM].describe() for f in fields(DroneParams)}
    for default in defaults:  # in composition order: a later file's comment wins, as its value does
        path = conf / f"{default.config_path}.yaml"
        if default.package is None or default.package.startswith("hydra") or not path.is_file():
            continue
        text = path.read_text(encoding="utf-8")
        meanings.update(key_comments(text, default.package))
        if default.package and not default.is_self:  # a group's option: its header says what it sets
            meanings.setdefault(default.package, _header(text))
    for group in names:  # a key its option leaves uncommented: the same key's comment in another option
        for path in sorted((conf / group).glob("*.yaml")):
            text = path.read_text(encoding="utf-8")
            package = re.search(r"^# @package (\S+)", text, re.MULTILINE)
            prefix = (package[1] if package else group.replace("/", ".")).replace("_global_", "")
            meanings = key_comments(text, prefix) | meanings
    values = OmegaConf.to_container(cfg, resolve=False)
    assert isinstance(values, dict)
    values.pop("hydra")
    keys = [(key, _show(value), meanings.get(key, "")) for key, value in _leaves(values)]
    return groups, keys


def _one_line(message: str) -> str:
    """Hydra's error message in one line: its statements, and the options it lists, comma-separated."""
    parts: list[str] = []
    for line in message.strip().splitlines():
        if line.startswith("Config search path"):  # then where it looked: not the user's mistake
            break
        if line.startswith("\t") and parts:  # an option of the group: "Available options in ...:" above
            parts[-1] += (" " if parts[-1].endswith(":") else ", ") + line.strip()
        elif line.strip() and not line.startswith(" ") and not line.startswith("To append"):
            parts.append(line.strip())
    return " ".join(f"{p}." if p[-1].isalnum() or p[-1] == "'" else p for p in parts)


def key_comments(text: str, package: str = "") -> dict[str, str]:
    """``{"checkpoint.keep_best": "also keep best.pt, ..."}``: each key's comment in a YAML text.

    Each key is put under ``package`` (``checkpoint``: ``checkpoint.keep_best``). A key's comment
    is the one on its line, else the block of comment lines right above it (no blank line between),
    up to its first line that ends a sentence. Lines of lists (``- item``) and
    of the ``defaults`` list are skipped.
    """
    out: dict[str, str] = {}
    parents: list[tuple[int, str]] = []
    block: list[str] = []
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("-"):
            block = []
            continue
        if stripped.startswith("#"):
            if not stripped.startswith("# @package"):
                block.append(stripped.lstrip("#").strip())
            continue
        match = _KEY_LINE.match(line)
        if match is None:  # a continued value: not a key
            block = []
            continue
        indent = len(match["indent"])
        while parents and parents[-1][0] >= indent:
            parents.pop()
        key = ".".join([k for _, k in parents] + [match["key"]])
        inline = _INLINE_COMMENT.search(match["rest"] or "")
        comment = inline["comment"].strip() if inline else _first_sentence(block)
        if comment and key != "defaults":
            out[f"{package}.{key}".lstrip(".")] = comment
        parents.append((indent, match["key"]))
        block = []
    return out


def _first_sentence(block: list[str]) -> str:
    """The first sentence of comment lines, as one line (a block's last ``:`` introduces a list)."""
    taken = []
    for line in block:
        taken.append(line)
        if line.endswith((".", ":")):
            break
    return _SENTENCE_END.split(" ".join(taken), maxsplit=1)[0].removesuffix(":")


# A full stop that ends a sentence: followed by a space, and not that of "e.g." or "i.e.".
_SENTENCE_END = re.compile(r"(?<=\.)(?<!e\.g\.)(?<!i\.e\.)\s+")


def _header(text: str) -> str:
    """The first sentence of a YAML file's opening comment block."""
    block = re.match(r"(?:[ \t]*#.*(?:\n|$))*", text)[0].splitlines()  # type: ignore[index]
    return _first_sentence(
        [line.strip().lstrip("#").strip() for line in block if not line.strip().startswith("# @package")]
    )


def _summary(path: Path, prefix: str = r"[\w-]+") -> str:
    """What a config does: its header, without the ``drone-xxx:`` (``prefix``, a regex) it starts with.

    An option in Hydra's ConfigStore (hydra/launcher=fused) has no file, and no summary.
    """
    return re.sub(rf"^{prefix}:\s*", "", _header(path.read_text("utf-8"))) if path.is_file() else ""


def _leaves(node: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    """``("env.mass", 1.0)`` for every key of a nested mapping; an empty mapping is a key too."""
    for key, value in node.items():
        if isinstance(value, Mapping) and value:
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def _show(value: Any) -> str:
    """A value as it is typed on the command line (YAML's spelling: null, true, [32, 32])."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list):
        return f"[{', '.join(_show(v) for v in value)}]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {_show(v)}" for k, v in value.items()) + "}"
    return str(value)
