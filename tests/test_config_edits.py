"""A run's config.json edited by hand: a change the newest checkpoint does not fit is refused
by field (nothing set aside as damaged, nothing written), and a file a hand edit broke is
named with its field and what it should hold, exit 2, one line."""
import json
import shutil
from pathlib import Path

import pytest

from hprior_jax import cli
from tests.test_life_cycle import _rows, _train, finished as base  # noqa: F401


def _listing(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.stat().st_mtime_ns
            for p in sorted(folder.rglob("*"))}


def _edit(run: Path, change) -> None:
    d = json.loads((run / "config.json").read_text())
    change(d)
    (run / "config.json").write_text(json.dumps(d, indent=2))


def _without_saved_configs(run: Path) -> None:
    """The checkpoints as written before they carried their configuration."""
    for path in (run / "checkpoints").glob("*/_CHECKPOINT_METADATA"):
        d = json.loads(path.read_text())
        d["custom_metadata"] = {}
        path.write_text(json.dumps(d))


@pytest.mark.parametrize("checkpoints", ["with their config", "written before"])
def test_a_config_the_checkpoint_does_not_fit_is_refused_and_nothing_is_moved(
        checkpoints, base, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(base, run)
    if checkpoints == "written before":
        _without_saved_configs(run)
    _edit(run, lambda d: d["sac"].update(hidden_dim=32))
    before = _listing(run)
    capsys.readouterr()
    for argv in (["train", "--resume", str(run), "--steps", "120", "--no-progress"],
                 ["eval", "--run", str(run), "--episodes", "2"]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "Traceback" not in err[0], err
        assert str(run / "config.json") in err[0], err
        says = ("sac.hidden_dim (16 there, 32 here)" if checkpoints == "with their config"
                else "does not fit the run's configuration")
        assert says in err[0], err
        if checkpoints == "with their config":  # refused before anything is written
            assert _listing(run) == before
        assert not (run / "broken_checkpoints").exists()
        assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["40", "80"]
    _edit(run, lambda d: d["sac"].update(hidden_dim=16))  # put back: it resumes from 80
    clean = tmp_path / "clean"
    shutil.copytree(base, clean)
    assert _train("--resume", str(clean), "--steps", "120") == 0
    assert _train("--resume", str(run), "--steps", "120") == 0
    assert _rows(run / "eval.csv") == _rows(clean / "eval.csv")


def _set(field, value):
    def change(d):
        *section, name = field.split(".")
        (d[section[0]] if section else d)[name] = value
    return change


@pytest.mark.parametrize("change, says", [
    ("{not json", "is not valid JSON (Expecting property name enclosed in double quotes: "
                  "line 1 column 2)"),
    ("[1, 2]", "holds list, not an object of fields"),
    (_set("steps", "abc"), "field 'steps' is \"abc\", expected an integer"),
    (_set("sac.lr", "fast"), "field 'sac.lr' is \"fast\", expected a number"),
    (_set("seeds", 3), "field 'seeds' is 3, expected a list of integers"),
    (_set("preset", "huge"), "field 'preset' is \"huge\", expected 'paper' or 'reduced' or "
                             "'smoke'"),
    (_set("sac", "big"), "field 'sac' is \"big\", expected an object of fields"),
    (_set("colour", "red"), "unknown field 'colour'"),
    (lambda d: d.pop("task"), "field(s) 'task' missing"),
    (lambda d: d.pop("algo"), "field(s) 'algo' missing"),
])
def test_a_hand_edited_config_json_is_named_with_its_field(change, says, base, tmp_path,
                                                          capsys):
    run = tmp_path / "run"
    shutil.copytree(base, run)
    if isinstance(change, str):
        (run / "config.json").write_text(change)
    else:
        _edit(run, change)
    before = _listing(run)
    capsys.readouterr()
    for argv in (["train", "--resume", str(run), "--no-progress"],
                 ["eval", "--run", str(run), "--episodes", "2"]):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: {run / 'config.json'}"), err
        assert says in err[0] and "repair it" in err[0], err
        assert _listing(run) == before
