"""Run-directory metric writers: JSONL (everything), CSV (evaluations), TensorBoard.

On resume, records after the restored checkpoint's step are dropped first: the resumed run
regenerates them exactly, so nothing that the checkpoint does not cover is duplicated, and
everything up to it is kept."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

EVAL_FIELDS = ("step", "seed", "true_return", "success")


class RunLog:
    def __init__(self, run_dir: Path, seeds, resume_step: int | None = None):
        self.dir = Path(run_dir)
        self.seeds = list(seeds)
        self.jsonl_path = self.dir / "metrics.jsonl"
        self.eval_csv_path = self.dir / "eval.csv"
        if resume_step is not None:
            self._truncate_after(resume_step)
        new_csv = not self.eval_csv_path.exists()
        self._jsonl = open(self.jsonl_path, "a")
        self._csv_file = open(self.eval_csv_path, "a", newline="")
        self._csv = csv.writer(self._csv_file)
        if new_csv:
            self._csv.writerow(EVAL_FIELDS)
        self._tb = self._open_tensorboard(resume_step)

    def _open_tensorboard(self, resume_step):
        try:
            from tensorboardX import SummaryWriter
        except ImportError:  # pragma: no cover - tensorboardX is a core dependency
            return {}
        return {s: SummaryWriter(str(self.dir / "tb" / f"seed_{s}"), purge_step=resume_step)
                for s in self.seeds}

    def _truncate_after(self, step: int) -> None:
        if self.jsonl_path.exists():
            keep = [l for l in self.jsonl_path.read_text().splitlines()
                    if l.strip() and json.loads(l)["step"] <= step]
            self.jsonl_path.write_text("".join(l + "\n" for l in keep))
        if self.eval_csv_path.exists():
            rows = list(csv.reader(self.eval_csv_path.open()))
            keep = [rows[0]] + [r for r in rows[1:] if int(r[0]) <= step]
            with self.eval_csv_path.open("w", newline="") as f:
                csv.writer(f).writerows(keep)

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
