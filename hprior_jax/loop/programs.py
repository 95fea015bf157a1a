"""Compiled programs by name: compiled ahead of time (so compile time is measured apart
from run time), or in a background thread before they are needed."""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial

import jax
import numpy as np


class ProgramCache:
    """The engine's programs, each compiled once per name."""

    def __init__(self):
        self._compiled: dict = {}
        self.compile_seconds: dict[str, float] = {}  # the wall time a program cost the run
        self.ahead_seconds: dict[str, float] = {}  # compile time spent ahead, in the background
        self._ahead: ThreadPoolExecutor | None = None
        self._pending: dict[str, Future] = {}

    def compile(self, name: str, fn, *args):
        """Compiles ahead of time so compile time is measured apart from run time (a program
        already compiling in the background, `compile_ahead`, is waited for: the wait is its
        cost to the run).

        Lowered from shapes and dtypes only: arrays restored from a checkpoint are committed
        to their device, and lowering from them would annotate the program with that
        placement, so a resumed run would miss the persistent compilation cache that a
        fresh run of the same shapes hits."""
        if name not in self._compiled:
            t0 = time.perf_counter()
            pending = self._pending.pop(name, None)
            if pending is not None and not pending.cancel():
                self._compiled[name], self.ahead_seconds[name] = pending.result()
            else:
                self._compiled[name] = lower_and_compile(fn, shapes(args))[0]
            self.compile_seconds[name] = time.perf_counter() - t0
        return self._compiled[name]

    def compile_ahead(self, name: str, fn, *args) -> None:
        """Starts compiling `fn` for `args`' shapes in a background thread, so a later
        `compile(name, ...)` finds it ready. XLA's CPU programs run on one core here and a
        compile on one core, so on two cores the compile of a later phase's programs costs
        the run little wall time."""
        self._in_background(name, partial(lower_and_compile, fn, shapes(args)))

    def _in_background(self, name: str, compile_it) -> None:
        """Runs `compile_it() -> (program, seconds)` on the background thread, in turn."""
        if name in self._compiled or name in self._pending:
            return
        if self._ahead is None:
            self._ahead = ThreadPoolExecutor(max_workers=1, thread_name_prefix="compile-ahead")
        self._pending[name] = self._ahead.submit(compile_it)

    def close(self) -> None:
        """Drops the background compiles not started (one in progress finishes)."""
        if self._ahead is not None:
            self._ahead.shutdown(wait=False, cancel_futures=True)
            self._ahead, self._pending = None, {}


def shapes(args):
    return jax.tree.map(abstract, args)


def lower_and_compile(fn, shapes):
    """-> (the compiled program, its compile seconds)."""
    return timed(lambda: fn.lower(*shapes).compile())


def timed(make):
    t0 = time.perf_counter()
    return make(), time.perf_counter() - t0


def abstract(x) -> jax.ShapeDtypeStruct:
    if isinstance(x, jax.ShapeDtypeStruct):
        return x
    weak = getattr(getattr(x, "aval", None), "weak_type", False)
    return jax.ShapeDtypeStruct(np.shape(x), np.result_type(x), weak_type=weak)
