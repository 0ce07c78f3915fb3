"""The README's Quick start and .ci/run stay in agreement; the CLI's front door works."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def quick_start_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    m = re.search(r"^#+\s*Quick ?start.*?^```[a-z]*\n(.*?)^```", text, re.S | re.M | re.I)
    assert m, "README has no Quick start block"
    return [line.strip() for line in m.group(1).splitlines() if line.strip()]


def test_quick_start_has_two_commands_and_ci_runs_the_second():
    cmds = quick_start_commands()
    assert len(cmds) == 2
    assert "carapost demo" in cmds[0]
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert cmds[1] in ci


def test_demo_runs(tmp_path):
    from carapost.cli import main

    assert main(["demo", "--out", str(tmp_path), "--frames", "3", "--markers", "35", "--no-progress"]) == 0
    assert (tmp_path / "Demo.cara").exists()


def test_cli_entry_point_help():
    out = subprocess.run([sys.executable, "-m", "carapost.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0 and "demo" in out.stdout
