"""README's Python example runs as written (in a scratch directory)."""
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
