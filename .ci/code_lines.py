"""Code lines of the package, per folder: no blank lines, comments or docstrings.

    python .ci/code_lines.py                     # drone_torchrl and hydra_plugins, per folder
    python .ci/code_lines.py benchmarks tests    # any folders

Python is read with ``tokenize`` (a string that is a whole statement is a docstring); C++ and CUDA
drop ``//`` and ``/* */`` comments and blank lines. Each line: ``code all path``; the last, the sum.
The size targets in the issues are counted this way.
"""

from __future__ import annotations

import io
import re
import sys
import tokenize
from pathlib import Path

SUFFIXES = (".py", ".cpp", ".cu", ".h", ".hpp")
_SKIP = {
    tokenize.COMMENT,
    tokenize.NL,
    tokenize.NEWLINE,
    tokenize.INDENT,
    tokenize.DEDENT,
    tokenize.ENDMARKER,
    tokenize.ENCODING,
}
_STATEMENT_START = {tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT}


def python_code_lines(text: str) -> int:
    """Lines holding a Python token that is neither a comment nor a docstring."""
    lines: set[int] = set()
    previous = None
    for token in tokenize.generate_tokens(io.StringIO(text).readline):
        if token.type in _SKIP:
            if token.type not in (tokenize.NL, tokenize.COMMENT):
                previous = token
            continue
        if token.type == tokenize.STRING and (previous is None or previous.type in _STATEMENT_START):
            previous = token  # a docstring
            continue
        lines.update(range(token.start[0], token.end[0] + 1))
        previous = token
    return len(lines)


def cpp_code_lines(text: str) -> int:
    """Non-blank lines outside ``/* */`` and ``//`` comments."""
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return sum(1 for line in text.splitlines() if line.strip() and not line.strip().startswith("//"))


def count(path: Path) -> tuple[int, int]:
    """``(code lines, all lines)`` of the source files under ``path``."""
    code = total = 0
    files = [path] if path.is_file() else sorted(path.rglob("*"))
    for file in files:
        if file.suffix not in SUFFIXES or not file.is_file():
            continue
        text = file.read_text(errors="replace")
        total += len(text.splitlines())
        code += python_code_lines(text) if file.suffix == ".py" else cpp_code_lines(text)
    return code, total


def main(argv: list[str]) -> None:
    """Print each folder's (and the package's top-level modules') counts, then the sum."""
    roots = [Path(arg) for arg in argv] or [Path("drone_torchrl"), Path("hydra_plugins")]
    code = total = 0
    for root in roots:
        parts = (
            [root]
            if root.name != "drone_torchrl"
            else [
                *sorted(p for p in root.iterdir() if p.is_dir() and p.name != "__pycache__"),
                *sorted(root.glob("*.py")),
            ]
        )
        top_code = top_total = 0
        for part in parts:
            c, t = count(part)
            code, total = code + c, total + t
            if part.is_dir() or root.name != "drone_torchrl":
                print(f"{c:6d} {t:6d} {part}")
            else:
                top_code, top_total = top_code + c, top_total + t
        if root.name == "drone_torchrl":
            print(f"{top_code:6d} {top_total:6d} {root}/*.py")
    print(f"{code:6d} {total:6d} total")


if __name__ == "__main__":
    main(sys.argv[1:])
