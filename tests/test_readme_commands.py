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
    assert command == "bash tools/setup.sh && .venv/bin/python -m pytest -n 2 --dist loadfile --durations=10"


def test_ci_runs_the_readme_demo_command():
    command = _readme_command("demo-command")
    assert command.startswith("bash tools/setup.sh && ") and "examples/deform_demo.py" in command
    assert (ROOT / "examples" / "deform_demo.py").exists()


def test_readme_operator_table_states_the_registry_defaults():
    # The "(CPU / GPU)" pair after each op's backends is what implementation=None picks; FFD's
    # row spells its per-basis CPU default out in words and is checked for those words.
    import re

    from geomjax._registry import REGISTRY

    readme = (ROOT / "README.md").read_text()
    table = readme[readme.index("<!-- ops-table:start -->") : readme.index("<!-- ops-table:end -->")]
    checked = set()
    for row in table.splitlines()[3:]:
        if not row.startswith("|"):
            continue
        cells = [c.strip() for c in row.strip("|").split("|")]
        names = re.findall(r"`(\w+)`", cells[0])
        pair = re.search(r"\((\w+) / (\w+)\)", cells[1])
        for name in names:
            declaration = REGISTRY[name]
            if pair is not None:
                assert (declaration.default_backend("cpu"), declaration.default_backend("gpu")) == pair.groups(), name
            elif "bernstein" in cells[1]:
                assert f"bernstein: {declaration.default_backend('cpu', 'bernstein')}" in cells[1], name
                assert f"local bases: {declaration.default_backend('cpu', 'bspline')} / {declaration.default_backend('gpu')}" in cells[1], name
            else:  # one backend, named alone
                assert cells[1] == "jax" and set(declaration.backends) == {"jax"}, name
            checked.add(name)
    assert checked == set(REGISTRY), sorted(set(REGISTRY) - checked)
