"""Comments say why, not when or how fast: no dates and no measured durations in the package's
comments and docstrings (measurements belong in the docs pages and benchmarks/, which say what
machine and load they were taken on)."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("drone_torchrl", "hydra_plugins")
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
# A number then a sub-second unit: "~2 ms", "20 us a call" (dt = 0.02 s and kilometres are fine).
DURATION = re.compile(r"\d\s?(ms|us|µs|ns)\b")


def _comments(path: Path) -> list[tuple[int, str]]:
    """The comments and the docstrings' lines of a Python or C++ file, with their line numbers."""
    text = path.read_text()
    if path.suffix == ".py":
        tokens = tokenize.generate_tokens(io.StringIO(text).readline)
        found = [(t.start[0], t.string) for t in tokens if t.type == tokenize.COMMENT]
        tree = ast.parse(text)
        documented = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
        for node in (n for n in ast.walk(tree) if isinstance(n, documented)):
            if docstring := ast.get_docstring(node):
                found += [(getattr(node, "lineno", 1), line) for line in docstring.splitlines()]
        return found
    return [(n, line[line.index("//") :]) for n, line in enumerate(text.splitlines(), 1) if "//" in line]


def test_no_dates_or_timings_in_comments():
    found = [
        f"{path.relative_to(ROOT)}:{line}: {comment.strip()}"
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*"))
        if path.suffix in (".py", ".cpp")
        for line, comment in _comments(path)
        if DATE.search(comment) or DURATION.search(comment)
    ]
    assert not found, "\n".join(found)


def test_the_check_finds_a_date_and_a_timing(tmp_path):
    assert DATE.search("# measured 2026-12-05") and DURATION.search("# costs ~2 ms an agent")
    module = tmp_path / "m.py"
    module.write_text('def f():\n    """Fast.\n\n    About 5 us a call.\n    """\n')
    assert _comments(module) == [(1, "Fast."), (1, ""), (1, "About 5 us a call.")]
    assert not DURATION.search("# one step (dt = 0.02 s)") and not DATE.search("# 2,000 episodes")
