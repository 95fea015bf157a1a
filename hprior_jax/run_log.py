"""Run-directory metric writers: JSONL (everything), CSV (evaluations), TensorBoard.

Every line is written whole by one write of a line-buffered file, so a kill leaves at most
one torn last line; the readers here drop such a line with a warning naming the file. On
resume, records after the restored checkpoint's step are dropped first: the resumed run
regenerates them exactly, so nothing that the checkpoint does not cover is duplicated, and
everything up to it is kept."""
from __future__ import annotations

import csv
import io
import json
import math
import threading
import warnings
from pathlib import Path

EVAL_FIELDS = ("step", "seed", "true_return", "success")


def read_jsonl(path: Path) -> list[dict]:
    """The records of a metrics.jsonl; a torn last line (a kill mid-write) is dropped with a
    warning, a bad line anywhere else is an error naming the file and line."""
    path = Path(path)
    lines = path.read_text().splitlines()
    records = []
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as e:
            if i == len(lines) - 1:
                warnings.warn(f"{path}: dropped a torn last line ({len(line)} characters; a "
                              "kill mid-write leaves one)", stacklevel=2)
                break
            raise ValueError(f"{path}, line {i + 1}: not a JSON record ({e.msg})") from None
    return records


def read_eval_rows(path: Path) -> list[list[str]]:
    """The rows of an eval.csv, header first; a torn last row is dropped with a warning."""
    path = Path(path)
    text = path.read_text()
    rows = [r for r in csv.reader(io.StringIO(text)) if r]
    if len(rows) > 1 and (len(rows[-1]) != len(EVAL_FIELDS) or not text.endswith("\n")):
        warnings.warn(f"{path}: dropped a torn last row {rows[-1]!r}", stacklevel=2)
        rows = rows[:-1]
    return rows


class RunLog:
    def __init__(self, run_dir: Path, seeds, resume_step: int | None = None):
        self.dir = Path(run_dir)
        self.seeds = list(seeds)
        self.jsonl_path = self.dir / "metrics.jsonl"
        self.eval_csv_path = self.dir / "eval.csv"
        if resume_step is not None:
            self._truncate_after(resume_step)
        new_csv = not self.eval_csv_path.exists() or self.eval_csv_path.stat().st_size == 0
        # line-buffered: each line reaches the file whole, in one write
        self._jsonl = open(self.jsonl_path, "a", buffering=1)
        self._csv_file = open(self.eval_csv_path, "a", newline="", buffering=1)
        self._csv = csv.writer(self._csv_file, lineterminator="\n")
        if new_csv:
            self._csv.writerow(EVAL_FIELDS)
        # importing tensorboardX takes ~1.3 s on a 2-core CPU: on a thread of its own, it
        # overlaps the first chunk (whose XLA run releases Python's lock) instead of coming
        # before the run's first env step
        self._writers: dict = {}
        self._open_error: BaseException | None = None
        self._opening = threading.Thread(target=self._open_tensorboard, args=(resume_step,),
                                         name="open-tensorboard", daemon=True)
        self._opening.start()

    @property
    def _tb(self) -> dict:
        """The TensorBoard writer of each seed (empty without tensorboardX)."""
        self._opening.join()
        if self._open_error is not None:  # raised where the writers are first used
            raise self._open_error
        return self._writers

    def _open_tensorboard(self, resume_step):
        # events at steps after the checkpoint are dropped (its own step's were kept)
        purge = None if resume_step is None else resume_step + 1
        try:
            from tensorboardX import SummaryWriter

            self._writers = {s: SummaryWriter(str(self.dir / "tb" / f"seed_{s}"),
                                              purge_step=purge) for s in self.seeds}
        except ImportError:  # pragma: no cover - tensorboardX is a core dependency
            pass
        except Exception as e:  # noqa: BLE001 - the main thread raises it (`_tb`)
            self._open_error = e

    def _truncate_after(self, step: int) -> None:
        if self.jsonl_path.exists():
            keep = [r for r in read_jsonl(self.jsonl_path) if r["step"] <= step]
            self.jsonl_path.write_text("".join(json.dumps(r) + "\n" for r in keep))
        if self.eval_csv_path.exists():
            rows = read_eval_rows(self.eval_csv_path)
            keep = rows[:1] + [r for r in rows[1:] if int(r[0]) <= step]
            with self.eval_csv_path.open("w", newline="") as f:
                csv.writer(f, lineterminator="\n").writerows(keep or [EVAL_FIELDS])

    def log(self, step: int, seed: int, metrics: dict) -> None:
        """Scalar metrics keyed `group/name` for one seed."""
        clean = {k: float(v) for k, v in metrics.items()}
        self._jsonl.write(json.dumps({"step": int(step), "seed": int(seed), **clean}) + "\n")
        tb = self._tb.get(seed)
        if tb is not None:
            for k, v in clean.items():
                if math.isfinite(v):
                    tb.add_scalar(k, v, step)

    def log_eval(self, step: int, seed: int, true_return: float, success: float | None) -> None:
        self._csv.writerow([int(step), int(seed), f"{true_return:.6g}",
                            "" if success is None else f"{success:.6g}"])
        metrics = {"eval/true_return": true_return}
        if success is not None:
            metrics["eval/success"] = success
        self.log(step, seed, metrics)

    def flush(self) -> None:
        self._jsonl.flush()
        self._csv_file.flush()
        for tb in self._tb.values():
            tb.flush()

    def close(self) -> None:
        self.flush()
        self._jsonl.close()
        self._csv_file.close()
        for tb in self._tb.values():
            tb.close()
