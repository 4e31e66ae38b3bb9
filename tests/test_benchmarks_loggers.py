"""``benchmarks/loggers.py`` at tiny sizes: its table's rows, and its read-back check catches a writer that differs."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Flushed mid-run too, so appending to an event file is part of what is compared.
TINY = [
    "--flush-every",
    "7",
    "--updates",
    "30",
    "--runs",
    "2",
    "--sweep-updates",
    "30",
    "--repeats",
    "1",
    "--import-repeats",
    "0",
]


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("loggers_benchmark", ROOT / "benchmarks" / "loggers.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


def rows(out: str) -> dict[tuple[str, str], list[str]]:
    """The timing table's rows, ``(writer, case) -> the other cells``."""
    cells = [line.strip("|").split("|") for line in out.splitlines() if line.startswith("| ")]
    return {(c[0].strip(), c[1].strip()): [x.strip() for x in c[2:]] for c in cells if len(c) == 7}


def test_every_writer_and_case_has_a_row_and_reads_back_equal(bench, capsys):
    bench.main(TINY)
    table = rows(capsys.readouterr().out)
    del table["writer", "case"]  # the header
    assert set(table) == {(w, c) for w in bench.WRITERS for c in bench.CASES}
    scalars = {"single run": 30 * 14, "population": 30 * 6, "fused sweep": 2 * 30 * 14}
    for (writer, case), (count, seconds, ratio, kib, equal) in table.items():
        assert int(count.replace(",", "")) == scalars[case]
        assert float(seconds) > 0 and int(kib) > 0
        assert equal == "yes"
        if writer == "hand-written":
            assert ratio == "1.0x"


def test_a_writer_that_logs_other_steps_is_caught(bench, capsys, monkeypatch):
    made = bench.Writer.__init__

    def shifted(self, kind, folder):  # TorchRL's logger writing every scalar one step late
        made(self, kind, folder)
        if kind == "TorchRL":
            log = self.log
            self.log = lambda scalars, step: log(scalars, step + 1)

    monkeypatch.setattr(bench.Writer, "__init__", shifted)
    with pytest.raises(SystemExit, match="did not read back equal"):
        bench.main([*TINY, "--updates", "3", "--sweep-updates", "3"])
    table = rows(capsys.readouterr().out)
    assert {case for (writer, case), cells in table.items() if cells[-1] == "NO"} == set(bench.CASES)
    assert all(
        cells[-1] == "yes"
        for (writer, _), cells in table.items()
        if writer in ("hand-written", "SummaryWriter")
    )


def test_the_baseline_writer_cannot_be_left_out(bench):
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--writers", "TorchRL"])
    assert exit_.value.code == 2
