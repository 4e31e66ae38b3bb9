"""The documentation's promises: its marked commands run, and its relative links lead somewhere.

A fenced ``bash`` or ``python`` block preceded by ``<!-- docs-test: run -->`` in README.md or a page
of docs/ is run in an empty folder and must exit 0 (docs/contributing.md: mark only blocks that
finish in seconds). Every relative link of README.md and of the pages (docs/*.md; drone-report's
summaries in docs/ subfolders are its output, not pages) must name a file that exists and, for a
markdown file, a heading it has.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- docs-test: run -->"
RUN_BLOCK = re.compile(re.escape(MARKER) + r"\s*\n```(bash|python)\n(.*?)\n```", re.S)
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)
BLOCK_TIMEOUT_S = 120
# The pages whose marked blocks must exist: an edit that loses the marker must not pass unnoticed.
PAGES_WITH_RUN_BLOCKS = {
    "docs/quickstart.md",
    "docs/training.md",
    "docs/environment.md",
    "docs/contributing.md",
}


def _markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _run_blocks() -> list:
    blocks = []
    for path in _markdown_files():
        for n, (language, code) in enumerate(RUN_BLOCK.findall(path.read_text())):
            where = f"{path.relative_to(ROOT)}#{n}"
            blocks.append(pytest.param(where, language, code, id=where))
    return blocks


def _slug(heading: str) -> str:
    """GitHub's (and MyST's ``myst_heading_anchors``) anchor of a heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text())
    return {_slug(line.lstrip("#")) for line in text.splitlines() if re.match(r"#+ ", line)}


def test_the_marked_blocks_are_where_the_pages_promise_them():
    assert {block.values[0].split("#")[0] for block in _run_blocks()} >= PAGES_WITH_RUN_BLOCKS


# Real commands, a minute in all on 2 cores: in the slow stage with the other real-command checks.
@pytest.mark.slow
@pytest.mark.parametrize(("where", "language", "code"), _run_blocks())
def test_a_marked_block_runs(tmp_path, where, language, code):
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "SDL_VIDEODRIVER": "dummy",
        "SDL_AUDIODRIVER": "dummy",
    }
    command = ["bash", "-e", "-c", code] if language == "bash" else [sys.executable, "-c", code]
    done = subprocess.run(
        command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S
    )
    assert done.returncode == 0, (
        f"{where} exited {done.returncode}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"
    )


def test_every_relative_link_points_to_a_file_that_exists():
    broken = []
    for path in _markdown_files():
        for target in LINK.findall(FENCE.sub("", path.read_text())):
            if re.match(r"[a-z]+:", target):
                continue  # https:, mailto:: not ours to check offline
            file, _, anchor = target.partition("#")
            linked = (path.parent / file).resolve() if file else path
            where = f"{path.relative_to(ROOT)}: {target}"
            if not linked.exists():
                broken.append(f"{where} (no such file)")
            elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
                broken.append(f"{where} (no such heading)")
    assert not broken, "\n".join(broken)
