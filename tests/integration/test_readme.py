"""The README's Concepts example runs exactly as written, and its two set-up commands exist."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
README = (REPO / "README.md").read_text()


@pytest.mark.slow  # default-tier budget; run with pytest -m slow tests/integration
def test_concepts_example_runs_as_written():
    from infinirl.runtime.worker import CRASH_LOG_DIR

    section = README.split("## Concepts", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=REPO)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err[-3000:]
    assert "sum of all observations: 360.0" in out
    # the example never shuts its groups down: leaving the Cluster does, its ranks' crash logs included
    # (their names carry the launching process; other runs on the machine may have logs of their own)
    assert not [p.name for p in CRASH_LOG_DIR.glob(f"*-{proc.pid}-*")]


def test_setup_commands_are_the_first_block_and_ci_runs_the_test_command():
    first_block = re.search(r"```bash\n(.*?)```", README, re.S).group(1).strip().splitlines()
    assert len(first_block) == 2
    install_and_run, test_command = (line.split("#")[0].strip() for line in first_block)
    assert install_and_run.endswith("infinirl train")
    ci = (REPO / ".ci" / "run").read_text()
    assert test_command in ci
