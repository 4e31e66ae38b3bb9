"""The figures the documentation repeats say the same thing on every page.

Two claims appear on several pages: how long the default tests take, and how close PPO flies to the
PD hover controller. Each is one figure everywhere (README.md, docs/*.md, pyproject.toml's
comment), and PPO's is the range of its rows in docs/beyond.md's measured table.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# A line that speaks of the default test run: its command (not `-m slow` and friends) or its name.
DEFAULT_TESTS = re.compile(r"python -m pytest(?! -m)|run the tests|default tests")
DURATION = re.compile(r"(?:about )?\d+(?:(?: to |-)\d+)? min(?:utes)?\b")
# "PPO ... 95.6-99.3% of the PD" or "PPO ... within 3% of the PD", within one sentence.
PPO_CLAIM = re.compile(r"\bPPO\b[^|.]*?((?:within )?\d+(?:\.\d+)?(?:-\d+(?:\.\d+)?)?%) of the PD")
TABLE_HEADING = "## REINFORCE, REINFORCE+, PPO and A2C against the PD controller"


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def test_every_mention_of_the_default_tests_time_is_the_same_figure():
    mentions = []
    for path in [*_pages(), ROOT / "pyproject.toml"]:
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            if DEFAULT_TESTS.search(line):
                where = f"{path.relative_to(ROOT)}:{number}"
                mentions += [(where, duration) for duration in DURATION.findall(line)]
    figures = {duration for _, duration in mentions}
    assert len(figures) == 1, f"the default tests' time differs between mentions: {mentions}"
    # The pages a new user reads first must say it: a rewording must not drop the figure unseen.
    files = {where.split(":")[0] for where, _ in mentions}
    assert files >= {"README.md", "docs/quickstart.md", "docs/contributing.md", "pyproject.toml"}


def _ppo_table_range() -> str:
    """The lowest and highest evaluation of PPO's seeds in docs/beyond.md's table, as ``lo-hi%``."""
    text = (ROOT / "docs" / "beyond.md").read_text()
    table = text[text.index(TABLE_HEADING) :].split("\n\n|", 1)[1].split("\n\n", 1)[0]
    algorithm, shares = "", []
    for row in table.splitlines():
        cells = [cell.strip() for cell in row.strip("|").split("|")]
        algorithm = cells[0] or algorithm  # a seed's row leaves the algorithm's cell empty
        if algorithm == "PPO":
            shares.append(float(re.search(r"\((\d+\.\d)%", cells[-2]).group(1)))
    assert len(shares) == 4, f"expected PPO's 4 seeds in the table, found {shares}"
    return f"{min(shares):.1f}-{max(shares):.1f}%"


def test_every_ppo_versus_pd_claim_is_the_measured_tables_range():
    measured = _ppo_table_range()
    claims = []
    for path in _pages():
        text = " ".join(path.read_text().split())  # a claim may wrap across lines
        claims += [(path.relative_to(ROOT).as_posix(), claim) for claim in PPO_CLAIM.findall(text)]
    assert {where for where, _ in claims} >= {"README.md", "docs/index.md", "docs/beyond.md"}
    wrong = [(where, claim) for where, claim in claims if claim != measured]
    assert not wrong, f"PPO's table says {measured} of PD; these claims differ: {wrong}"
