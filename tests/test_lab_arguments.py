"""`hprior reward-lab` checks every argument before any work: one line, exit 2, no dataset
loaded or built, nothing written (no --out, no .lock, no cache)."""
import pytest

from hprior_jax import cli
from hprior_jax.lab import dataset


@pytest.mark.parametrize("bad, says", [
    (["--budgets", "0"], "--budgets 0: budgets must be increasing positive label counts"),
    (["--budgets", "-5", "10"], "--budgets -5 10: budgets must be increasing positive"),
    (["--budgets", "100", "25"], "--budgets 100 25: budgets must be increasing"),
    (["--rules", "pebble", "nonsense"], "--rules: unknown lab rule ['nonsense']; available:"),
    (["--rules", "pebble", "pebble"], "--rules: a rule is named twice"),
    (["--rules", "pebble@3"], "--rules: ['pebble'] train no prior term"),
    (["--seeds", "0"], "--seeds 0: give the number of seeds, at least 1"),
    (["--seeds", "-3"], "--seeds -3: give the number of seeds"),
    (["--teacher", "grumpy"], "--teacher: unknown teacher 'grumpy'"),
    (["--prior-set", "wm_layers=two"], "--prior-set: setting 'wm_layers=two': wm_layers is"),
    (["--queries-per-round", "0"], "--queries-per-round 0: give at least 1"),
    (["--dataset-steps", "0"], "--dataset-steps 0: give a positive step count"),
    (["--contrasts", "prior"], "--contrasts: contrast 'prior': write A:B"),
])
def test_a_bad_lab_argument_is_refused_before_any_work(bad, says, tmp_path, monkeypatch,
                                                      capsys):
    monkeypatch.setenv("HPRIOR_LAB_CACHE", str(tmp_path / "cache"))
    started = []
    monkeypatch.setattr(dataset, "load_or_build",  # a build: minutes, so never started here
                        lambda *a, **k: started.append(a) or (_ for _ in ()).throw(
                            AssertionError("the dataset build started")))
    argv = ["reward-lab", "--task", "toy_point", "--preset", "smoke", *bad,
            "--out", str(tmp_path / "lab")]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and says in err[0], err
    assert not started and not any(tmp_path.iterdir())


def test_the_lab_and_its_report_are_one_command_with_their_own_help(capsys):
    """`hprior reward-lab --help` points to `hprior reward-lab report`, whose own help is
    the report's arguments; the lab's --task stays required without `report`."""
    with pytest.raises(SystemExit) as e:
        cli.main(["reward-lab", "--help"])
    assert e.value.code == 0 and "hprior reward-lab report RESULTS_CSV" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        cli.main(["reward-lab", "report", "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0 and out.startswith("usage: hprior reward-lab report")
    assert "--tags" in out and "--task" not in out
    with pytest.raises(SystemExit) as e:
        cli.main(["reward-lab", "--seeds", "3"])
    assert e.value.code == 2 and "--task" in capsys.readouterr().err
