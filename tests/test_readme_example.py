"""README's Python example runs as written (in a scratch directory); CI runs README's set-up
commands as written."""
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"


def _example() -> str:
    text = README.read_text()
    found = re.search(r"<!-- api-example[^>]*-->\n```python\n(.*?)```", text, re.S)
    assert found, "README lost its api-example block"
    return found.group(1)


@pytest.mark.slow  # cheetah's programs: minutes on 2 cores
def test_the_readme_python_example_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    scope = {}
    exec(compile(_example(), "README.md", "exec"), scope)
    assert scope["frame"].shape == (240, 320, 3)
    assert (scope["run_dir"] / "eval.csv").exists()
    assert scope["returns"].shape == (4,)


def test_the_readme_example_uses_only_the_public_api():
    import hprior_jax

    used = set(re.findall(r"hprior_jax\.(\w+)", _example()))
    assert used <= set(hprior_jax.__all__) | {"presets"}, used - set(hprior_jax.__all__)


def test_ci_runs_exactly_the_readme_set_up_commands():
    block = re.search(r"## Set-up: two commands.*?```bash\n(.*?)```", README.read_text(), re.S)
    assert block, "README lost its set-up block"
    readme = [line for line in block.group(1).splitlines() if line and not line.startswith("#")]
    ci = (README.parent / ".ci" / "run").read_text().splitlines()
    called = [line.split("#")[0].strip() for line in ci
              if line and not line.startswith(("#", "set ", "cd ", "export "))]
    assert len(readme) == 2 and called == readme, (readme, called)
