"""The library's shape, checked: small files, short functions, no project import hidden in a
function outside the command line, imports one way through the layers (`lint-imports`,
pyproject.toml), no dates in code."""
import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SOURCES = sorted(p for folder in ("hprior_jax", "tasks") for p in (ROOT / folder).rglob("*.py"))
MAX_FILE_LINES, MAX_FUNCTION_LINES = 400, 80
# start-up: import what is used (the command line; the packages' entry points, whose registry
# and API load their heavy parts on first use)
LAZY_ALLOWED = ("hprior_jax/cli.py", "hprior_jax/commands/", "tasks/__init__.py",
                "hprior_jax/__init__.py")


def _name(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _functions(tree):
    return [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def test_no_file_over_400_lines_and_no_function_over_80():
    long_files = [f"{_name(p)}: {n}" for p in SOURCES
                  if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES]
    long_functions = [f"{_name(p)}:{f.lineno} {f.name}: {f.end_lineno - f.lineno + 1}"
                      for p in SOURCES for f in _functions(ast.parse(p.read_text()))
                      if f.end_lineno - f.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long_files and not long_functions, (long_files, long_functions)


def test_no_project_import_inside_a_function_outside_the_command_line():
    hidden = []
    for p in SOURCES:
        if _name(p).startswith(LAZY_ALLOWED):
            continue
        for f in _functions(ast.parse(p.read_text())):
            for node in ast.walk(f):
                module = (node.module if isinstance(node, ast.ImportFrom) else
                          node.names[0].name if isinstance(node, ast.Import) else None)
                if module and module.split(".")[0] in ("hprior_jax", "tasks"):
                    hidden.append(f"{_name(p)}:{node.lineno} {module}")
    assert not hidden, hidden


@pytest.mark.parametrize("where", ["code", "README.md"])
def test_no_dates(where):
    date = re.compile(r"20\d{2}-\d{2}-\d{2}")
    paths = SOURCES if where == "code" else [ROOT / "README.md"]
    found = [f"{_name(p)}:{i + 1}" for p in paths
             for i, line in enumerate(p.read_text().splitlines()) if date.search(line)]
    assert not found, found


def test_the_command_line_and_the_task_registry_load_without_jax():
    """`hprior --help`, `hprior methods` and the task registry import no jax: a command pays
    for jax, flax and mujoco only when it runs something that needs them."""
    import subprocess
    import sys

    code = ("import sys, hprior_jax, hprior_jax.cli, tasks; tasks.names(); "
            "heavy = sorted(m for m in ('jax', 'flax', 'optax', 'mujoco', 'orbax') "
            "if m in sys.modules); print(heavy); assert not heavy")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr



def test_the_architecture_page_names_modules_that_exist():
    text = (ROOT / "docs" / "architecture.md").read_text()
    paths = set(re.findall(r"`((?:hprior_jax|tasks)/[\w/]*(?:\.py|/))`", text))
    assert len(paths) > 20, paths
    missing = sorted(p for p in paths if not (ROOT / p).exists())
    assert not missing, missing


def test_imports_run_one_way_through_the_layers():
    """import-linter's contract in pyproject.toml (the layers, from commands down to tasks)."""
    lint = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml")], cwd=ROOT,
                          capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stdout + done.stderr
