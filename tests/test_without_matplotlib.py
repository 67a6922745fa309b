"""Commands that draw figures still run without matplotlib (the bare wheel): they write their
tables and say in one line how to get the figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from nanostage.cli import main


@pytest.mark.usefixtures("without_matplotlib")
def test_reproduce_without_matplotlib_writes_the_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r"
    assert main(["reproduce", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert (out / "summary.json").is_file()
    assert not (out / "steps.png").exists()
    assert "| " in captured.out
    assert captured.err.strip().count("\n") == 0
    assert 'pip install "nanostage[plot]"' in captured.err
