"""The README's quick-start commands are what CI runs: check .ci/run can find them."""

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_command(marker: str) -> str:
    script = (ROOT / ".ci" / "run").read_text()
    function = script[script.index("readme_command() {") : script.index("\n}\n") + 3]
    out = subprocess.run(["bash", "-c", f"{function}\nreadme_command {marker}"], cwd=ROOT, capture_output=True, text=True, check=True)
    return out.stdout.strip()


def test_ci_runs_the_readme_test_command():
    command = _readme_command("test-command")
    assert command == "bash tools/setup.sh && .venv/bin/python -m pytest -n 2 --dist loadfile"


def test_ci_runs_the_readme_demo_command():
    command = _readme_command("demo-command")
    assert command.startswith("bash tools/setup.sh && ") and "examples/deform_demo.py" in command
    assert (ROOT / "examples" / "deform_demo.py").exists()
