"""`hprior` command line: parse, then call into the library (no JAX logic here).

    hprior train --task cheetah_run --algo sac --preset smoke
    hprior train --task cheetah_run --seeds 12345 23456 --steps 100000 --sac.lr 3e-4
    hprior train --resume runs/cheetah_run_sac_20261122-101500
    hprior eval --run runs/cheetah_run_sac_20261122-101500 --episodes 20 --video
    hprior export --run runs/cheetah_run_prior_20261122-101500 --seed 12345 --out my_reward
    hprior attention --run runs/cheetah_run_prior_20261122-101500 --pair 3
    hprior grid --tasks cheetah_run --algos sac pebble prior --preset reduced --out results
    hprior report results
    hprior reward-lab --task cheetah_run --seeds 20 --budgets 25 100 400
    hprior reward-lab report runs/reward_lab/cheetah_run/results.csv lab_report
    hprior tasks
    hprior methods
"""
from __future__ import annotations

import difflib
import os
import signal
import sys

import hprior_jax

if __name__ == "__main__":  # python -m hprior_jax.cli: as the `hprior` script does
    hprior_jax._quiet_ctrl_c_while_importing()

from tasks import _xla_flags  # noqa: F401,E402  (before anything imports jax)

from hprior_jax.commands import grid, label, reward_lab, train, trained_runs  # noqa: E402
from hprior_jax.methods import registry  # noqa: E402

USAGE = """usage: hprior COMMAND [ARGS]

commands:
  train      train an agent (hprior train --help for every option)
  eval       evaluate a run's checkpoint per seed (true return, success), optionally a video
  export     a seed's learned reward and policy as a standalone folder (hprior_jax.load_reward)
  label      label preference queries in a browser (a local web app)
  attention  world-model attention maps of a trained run of a method with a world model
  grid       every (task, algorithm) with its seeds; skips finished runs, resumes the rest
  report     Tables 6-7, paired t-tests, learning curves of a grid's results directory
  reward-lab which method learns the better reward from the same labels, on fixed data
             (reward-lab report: a lab's report again, or several labs' merged)
  tasks      list the registered tasks
  methods    list the registered methods (--algo)

options:
  -h, --help     this message
  -V, --version  the version and git commit
"""


def _tasks(argv: list[str]) -> int:
    from hprior_jax.envs import task_names

    print("\n".join(task_names()))
    return 0


def _methods(argv: list[str]) -> int:
    print(registry.describe())
    return 0


def main(argv: list[str] | None = None) -> int:
    from hprior_jax.dir_lock import DirInUse

    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE, file=sys.stdout if argv else sys.stderr)  # bare `hprior`: a usage error
        return 0 if argv else 2
    if argv[0] in ("--version", "-V"):
        from hprior_jax.provenance import version_string

        print(version_string())
        return 0
    command, rest = argv[0], argv[1:]
    commands = {"train": train.train, "eval": trained_runs.evaluate,
                "export": trained_runs.export, "label": label.label,
                "attention": trained_runs.attention, "grid": grid.grid, "report": grid.report,
                "reward-lab": reward_lab.reward_lab, "tasks": _tasks, "methods": _methods}
    if command not in commands:
        close = difflib.get_close_matches(command, commands, n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        print(f"unknown command {command!r}{hint}\n\n{USAGE}", file=sys.stderr)
        return 2
    try:
        if signal.getsignal(signal.SIGINT) is hprior_jax._quit_on_ctrl_c:
            # the command's own: KeyboardInterrupt below, `hprior train`'s StopRequest
            signal.signal(signal.SIGINT, signal.default_int_handler)
        return commands[command](rest)
    except BrokenPipeError:  # the reader went away (`hprior train --help | head -1`)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # the exit's flush has nowhere to fail
        return 141  # as a process the pipe's signal ended
    except (ValueError, FileExistsError, FileNotFoundError, NotADirectoryError,
            PermissionError, DirInUse) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # disk full, permission lost mid-run: the path and the cause
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # before training started (a run saves on its own Ctrl-C)
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
