"""What a run shows while it trains: the progress bar (env steps per second over all seeds,
compiles excluded, the latest evaluation) and the wall time of each part of a loop
iteration."""
from __future__ import annotations

import contextlib
import os
import sys
import time
from pathlib import Path


class ProgressBar:
    """tqdm with one rate, env steps per second over all seeds, from the wall time of the
    training parts only (compiles excluded), and the ETA from that rate; the latest
    evaluation (return, and success rate where the task has one) beside it, and the share
    of that wall time evaluation has taken so far (its cost: see `--num-eval-episodes`)."""

    def __init__(self, total: int, initial: int, enabled: bool, num_seeds: int,
                 has_success: bool):
        from tqdm.auto import tqdm

        self.total, self.done, self.num_seeds = total, initial, num_seeds
        self.has_success = has_success
        self.steps, self.seconds, self.eval_seconds = 0, 0.0, 0.0
        self._eval = ""
        # a log file gets a plain line per evaluation instead of the bar's \r frames
        self.lines = enabled and not sys.stderr.isatty()
        self._bar = tqdm(total=total, initial=initial, unit="step",
                         disable=not enabled or self.lines, dynamic_ncols=True,
                         mininterval=1.0,
                         bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} {postfix}")
        self._status = ""

    def advance(self, length: int, seconds: float) -> None:
        self.done += length
        self.steps += length
        self.seconds += seconds
        rate = self.steps / max(self.seconds, 1e-9)  # per seed
        eta = (self.total - self.done) / rate
        cost = (f" (evaluation {100 * self.eval_seconds / self.seconds:.0f}% of the time)"
                if self.eval_seconds else "")
        self._status = (f"{rate * self.num_seeds:.0f} env steps/s, ETA {clock(eta)}"
                        f"{self._eval}{cost}")
        self._bar.set_postfix_str(self._status, refresh=False)
        self._bar.update(length)
        if self.lines and self._eval:  # once per evaluation
            self.write(f"step {self.done}/{self.total}: {self._status}")
            self._eval = ""

    def evaluated(self, mean_return: float, mean_success: float, seconds: float) -> None:
        self.eval_seconds += seconds
        self._eval = f", eval return {mean_return:.1f}"
        if self.has_success:
            self._eval += f", success {100 * mean_success:.0f}%"

    def write(self, line: str) -> None:
        self._bar.write(line, file=sys.stdout)
        sys.stdout.flush()

    def close(self) -> None:
        self._bar.close()


def clock(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class WallTimer:
    """Wall seconds per named part of one loop iteration, less any compile that happened
    inside it (`compile_seconds` is the engine's dict of program -> compile time, which
    grows when a new program is compiled); compile time is summed under `compile_s`."""

    def __init__(self, compile_seconds: dict):
        self.compile_seconds = compile_seconds
        self.seconds = {"compile_s": 0.0}

    @contextlib.contextmanager
    def __call__(self, part: str):
        before, t0 = set(self.compile_seconds), time.perf_counter()
        yield
        compiled = sum(v for k, v in self.compile_seconds.items() if k not in before)
        self.seconds["compile_s"] += compiled
        self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - t0 - compiled

    def move(self, source: str, part: str, seconds: float) -> None:
        """Counts `seconds` of `source` under `part` instead."""
        self.seconds[source] -= seconds
        self.seconds[part] = self.seconds.get(part, 0.0) + seconds


def process_age() -> float:
    """Seconds since this process started (Linux: from /proc; elsewhere: since this module
    was imported, which misses the interpreter's start and the first imports)."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.perf_counter() - _IMPORTED


_IMPORTED = time.perf_counter()
