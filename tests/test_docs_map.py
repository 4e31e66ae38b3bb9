"""docs/engines.md's module map stays true: it lists every module of the package and no other, and
every ``file:function`` the page names exists (no import: the files are parsed)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "engines.md"
PACKAGES = ("drone_torchrl", "hydra_plugins")
SOURCE_SUFFIXES = (".py", ".cpp")
MAP_HEADING = "### Module map"
# `path/to/file.py:Name` or `...cpp:Name`, Name possibly Class.method.
NAMED = re.compile(r"`([\w/]+\.(?:py|cpp)):([A-Za-z_][\w.]*)`")
# A C++ function's definition: qualifiers, a return type, the name, its parameter list.
CPP_DEFINITION = (
    r"^(?:template <[^>]*>\s*)?(?:(?:DK_HD|static|inline|constexpr|extern \"C\")\s+)*[\w:<>]+[\s*&]+{name}\("
)


def _package_modules() -> set[str]:
    return {
        p.relative_to(ROOT).as_posix()
        for package in PACKAGES
        for p in (ROOT / package).rglob("*")
        if p.suffix in SOURCE_SUFFIXES and p.is_file() and "__pycache__" not in p.parts
    }


def _section(text: str, heading: str) -> str:
    assert heading + "\n" in text, f"docs/engines.md has no {heading!r} section"
    start = text.index(heading + "\n") + len(heading)
    following = re.search(r"^#{2,3} ", text[start:], re.M)
    return text[start : start + following.start()] if following else text[start:]


def mapped_modules(text: str) -> list[str]:
    """The modules the map's table lists: its first cell's folder joined to each file named in the second."""
    modules = []
    for line in _section(text, MAP_HEADING).splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if not line.startswith("|") or len(cells) < 2 or set(cells[0]) <= {"-"} or cells[0] == "folder":
            continue
        folder = re.match(r"`([\w/]+/)`", cells[0])
        assert folder, f"docs/engines.md's module map: a row without a `folder/`: {line[:80]}"
        names = re.findall(r"`([\w]+\.(?:py|cpp))`", cells[1])
        modules += [folder.group(1) + name for name in names]
    return modules


def defines(path: Path, name: str) -> bool:
    """Whether ``path`` defines ``name`` (``Class.method`` for a method) at its top level."""
    text = path.read_text()
    if path.suffix == ".cpp":
        return re.search(CPP_DEFINITION.format(name=re.escape(name)), text, re.M) is not None
    scope: list[ast.stmt] = ast.parse(text).body
    for part in name.split("."):
        found = [
            node
            for node in scope
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name == part
        ]
        if not found:
            return False
        scope = found[0].body
    return True


def test_the_module_map_lists_every_module_once_and_nothing_else():
    listed = mapped_modules(PAGE.read_text())
    actual = _package_modules()
    assert len(actual) > 90  # the walk found the package
    repeated = sorted({m for m in listed if listed.count(m) > 1})
    assert not repeated, f"docs/engines.md's module map lists these twice: {repeated}"
    assert not actual - set(listed), (
        f"modules missing from docs/engines.md's map: {sorted(actual - set(listed))}"
    )
    assert not set(listed) - actual, (
        f"docs/engines.md's map lists modules that do not exist: {sorted(set(listed) - actual)}"
    )


def test_every_file_and_function_the_page_names_exists():
    named = NAMED.findall(PAGE.read_text())
    # The four concepts the map promises, on both engines.
    assert {
        ("drone_torchrl/algorithms/ppo.py", "OnPolicy.learn"),
        ("drone_torchrl/objectives/reinforce.py", "reinforce_terms"),
        ("drone_torchrl/kernels/drone_kernels.cpp", "reinforce_agent"),
        ("drone_torchrl/envs/drone_env.py", "DroneEnv._step"),
        ("drone_torchrl/kernels/drone_kernels.cpp", "fly_block"),
        ("drone_torchrl/schema.py", "Rule.check"),
    } <= set(named)
    missing = [
        f"{path}:{name}"
        for path, name in named
        if not (ROOT / path).is_file() or not defines(ROOT / path, name)
    ]
    assert not missing, f"docs/engines.md names what does not exist: {missing}"


def test_the_checks_catch_what_they_are_for():
    """A module the map leaves out or makes up, and a function that is not there, are each seen."""
    row = "| `drone_torchrl/envs/` | `dynamics.py` the physics · `made_up.py` nothing |\n"
    text = f"{MAP_HEADING}\n\n| folder | module |\n|---|---|\n{row}\n## Next\n"
    assert mapped_modules(text) == ["drone_torchrl/envs/dynamics.py", "drone_torchrl/envs/made_up.py"]
    assert defines(ROOT / "drone_torchrl/algorithms/ppo.py", "OnPolicy.learn")
    assert not defines(ROOT / "drone_torchrl/algorithms/ppo.py", "OnPolicy._no_such_step")
    assert not defines(ROOT / "drone_torchrl/algorithms/ppo.py", "learn")  # a method is not top-level
    assert defines(ROOT / "drone_torchrl/kernels/drone_kernels.cpp", "drone_step")
    assert not defines(ROOT / "drone_torchrl/kernels/drone_kernels.cpp", "fly_episode")
