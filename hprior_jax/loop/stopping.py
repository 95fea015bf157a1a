"""How a run stops early: Ctrl-C (after the chunk in flight, with a checkpoint), a person's
round that stops waiting, a loss that is no longer finite. `hprior train` installs the Ctrl-C
handler first, before it checks the configuration or builds the engine."""
from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path


class TrainingDiverged(RuntimeError):
    pass


class Interrupted(Exception):
    """The user pressed Ctrl-C (the chunk in flight finished), or a person's round stopped
    waiting for answers: a checkpoint of step `step` is in the run directory."""

    def __init__(self, run_dir: Path, step: int, why: str = ""):
        super().__init__(f"interrupted at step {step}{': ' + why if why else ''}; "
                         f"checkpoint saved in {run_dir}")
        self.run_dir, self.step = run_dir, step


class StopRequest:
    """SIGINT handler for the run: the first Ctrl-C is a request to stop after the chunk in
    flight (XLA cannot be interrupted mid-program anyway), the second stops at once. Only
    the main thread can own signals; elsewhere Ctrl-C keeps its default behaviour."""

    def __init__(self):
        self.requested = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        print("\nCtrl-C: stopping at the next safe point (once training has started: after "
              "the chunk in flight, with a checkpoint); press Ctrl-C again to stop at once "
              "and lose that chunk", file=sys.stderr, flush=True)

    def restore(self):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
