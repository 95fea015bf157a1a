"""The command line's small courtesies: a reader that goes away (`| head -1`) ends the command
quietly, a mistyped command gets a suggestion, `hprior --help` lists --version, and `train
--help` names every flag a resume may change."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hprior_jax import cli
from hprior_jax.config import CHANGEABLE_ON_RESUME

ROOT = Path(__file__).resolve().parent.parent


def test_a_closed_pipe_ends_help_quietly():
    read, write = os.pipe()
    os.close(read)  # the reader is gone before anything is written: every write fails
    try:
        proc = subprocess.run([sys.executable, "-m", "hprior_jax.cli", "train", "--help"],
                              cwd=ROOT, stdout=write, stderr=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)
    finally:
        os.close(write)
    assert proc.stderr == "" and proc.returncode == 141, proc.stderr


def test_a_mistyped_command_gets_a_suggestion_and_help_lists_version(capsys):
    assert cli.main(["trian"]) == 2
    assert capsys.readouterr().err.startswith("unknown command 'trian'; did you mean 'train'?")
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--version" in out
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("hprior_jax ")


def test_train_help_names_every_flag_a_resume_may_change(capsys):
    with pytest.raises(SystemExit):
        cli.main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    resume = text[text.index("--resume DIR continues"):].split(" may change")[0]
    for name in CHANGEABLE_ON_RESUME:
        assert "--" + name.replace("_", "-") in resume, (name, resume)


@pytest.mark.parametrize("argv, says", [
    (["label", "--dir", "{dir}", "--port", "99999"], "--port 99999: a port is 1-65535"),
    (["label", "--dir", "{dir}", "--port", "-1"], "--port -1: a port is 1-65535"),
    (["label", "--dir", "{dir}", "--host", "300.1.1.1"],
     "--host 300.1.1.1: this machine cannot serve on it"),
    (["label", "--dir", "{dir}", "--host", "192.0.2.1"],  # a documentation address: not ours
     "--host 192.0.2.1: this machine cannot serve on it"),
    (["train", "--task", "toy_point", "--algo", "pebble", "--teacher", "human", "--preset",
      "smoke", "--label-port", "70000", "--out", "{dir}"], "--label-port 70000: a port is"),
])
def test_a_labelling_address_is_checked_before_anything_is_written(argv, says, tmp_path,
                                                                   capsys):
    (tmp_path / "queries").mkdir()
    (tmp_path / "queries" / "queries.jsonl").write_text("")  # a query folder (empty)
    argv = [a.format(dir=tmp_path / ("queries" if argv[0] == "label" else "run"))
            for a in argv]
    before = sorted(tmp_path.rglob("*"))
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {says}"), err
    assert sorted(tmp_path.rglob("*")) == before
