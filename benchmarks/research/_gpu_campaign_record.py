"""The record of `benchmarks/research/gpu_campaign.py`: files written whole, the plan of what fits
the time left, the decision rules' verdicts (results/research/gpu_campaign/README.md), and the
campaign's clock, log and watchdog."""
from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
import threading
import time
from pathlib import Path

# decision rules (README, written before any run)
SKILL_MIN, POSITION_R2_MIN = 0.70, 0.95
T_STAR_OVER_UNIFORM_MIN, REVEAL_ERROR_MAX = 10.0, 0.5


# -- files ------------------------------------------------------------------------------
def write_atomic(path: Path, text: str) -> Path:
    """`text` to `path`, whole or not at all (a temporary name, then renamed)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def write_csv(rows: list[dict], path: Path) -> Path:
    buf = io.StringIO()
    columns = list(dict.fromkeys(k for row in rows for k in row))
    writer = csv.DictWriter(buf, fieldnames=columns, restval="", lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return write_atomic(path, buf.getvalue())


# -- planning (pure) -------------------------------------------------------------------------
@dataclasses.dataclass
class Item:
    name: str
    estimate_s: float
    needs: str | None = None  # an item that must have run first


def plan(items: list[Item], seconds_left: float) -> list[dict]:
    """Admit `items` in order while their estimates add up to at most `seconds_left`; an item
    whose `needs` was dropped is dropped too. -> [{item, estimate_s, admitted, why}]."""
    out, used, dropped = [], 0.0, set()
    for it in items:
        if it.needs in dropped:
            why, ok = f"needs {it.needs}, which will not run", False
        elif used + it.estimate_s > seconds_left:
            why, ok = (f"needs ~{it.estimate_s:.0f} s, {max(seconds_left - used, 0):.0f} s "
                       "left after the items before it"), False
        else:
            why, ok = "", True
            used += it.estimate_s
        if not ok:
            dropped.add(it.name)
        out.append(dict(item=it.name, estimate_s=round(it.estimate_s, 1), admitted=ok, why=why))
    return out


def world_model_verdict(mean: dict) -> str:
    skill, r2 = mean["wm/skill_vs_persistence"], mean["alpha/position_r2"]
    head = f"skill {skill:.3f}, position R² {r2:.3f} (means over seeds): "
    if skill < SKILL_MIN:
        return head + f"undecided (skill below {SKILL_MIN})"
    if r2 >= POSITION_R2_MIN:
        return head + "holds: the small model is not why α is positional on cheetah"
    return head + (f"does not hold: with a predicting model α is less than "
                   f"{POSITION_R2_MIN:.0%} position at this size")


def probe_verdict(row: dict) -> str:
    over, err = row["alpha_t_star_over_uniform"], row["reveal_error_over_predict_zero"]
    head = f"α on t* {over:.1f}x uniform, reveal error {err:.2f} of predicting zero: "
    if over > T_STAR_OVER_UNIFORM_MIN and err < REVEAL_ERROR_MAX:
        return head + "holds: size restores the look-back"
    if err < REVEAL_ERROR_MAX:
        return head + "the prediction looks back, α does not show it"
    return head + "not restored: the model does not learn the reveal"


# -- the campaign -----------------------------------------------------------------------------
class Campaign:
    """The record (campaign.json, rewritten whole after every step), the log and the clock."""

    def __init__(self, out: Path, budget_s: float, record: dict, t0: float):
        self.out, self.budget_s, self.t0 = out, budget_s, t0
        self.record = {**record, "done": [], "dropped": [], "finished": False}
        self.running = "start-up"
        self._lock = threading.Lock()
        out.mkdir(parents=True, exist_ok=True)

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def left(self) -> float:
        return self.budget_s - self.elapsed()

    def say(self, line: str) -> None:
        line = f"[{self.elapsed():6.1f} s] {line}"
        print(line, flush=True)
        with open(self.out / "log.txt", "a") as f:
            f.write(line + "\n")

    def save(self, timeout: float = -1) -> None:
        if not self._lock.acquire(timeout=timeout):
            return
        try:
            self.record["elapsed_s"] = round(self.elapsed(), 1)
            write_atomic(self.out / "campaign.json",
                         json.dumps(self.record, indent=2, default=str))
        finally:
            self._lock.release()

    def drop(self, item: str, why: str) -> None:
        self.say(f"DROPPED {item}: {why}")
        self.record["dropped"].append(dict(item=item, why=why))
        self.save()

    def done(self, item: str, seconds: float) -> None:
        self.record["done"].append(dict(item=item, seconds=round(seconds, 1)))
        self.save()

    def fits(self, item: str, estimate_s: float, reserve_s: float) -> bool:
        """Whether `item` (~estimate_s) still fits the time left; drops it if not."""
        left = self.left() - reserve_s
        if estimate_s > left:
            self.drop(item, f"needs ~{estimate_s:.0f} s, {max(left, 0):.0f} s left")
            return False
        return True

    def watchdog(self, hard_s: float) -> threading.Timer:
        """Ends the process at `hard_s` seconds of campaign time, whatever runs."""
        def fire():
            self.record["hard_stop"] = f"at {hard_s:.0f} s while running {self.running}"
            self.say(f"HARD STOP {self.record['hard_stop']}")
            self.save(timeout=5)
            os._exit(3)

        timer = threading.Timer(max(hard_s - self.elapsed(), 0.0), fire)
        timer.daemon = True
        timer.start()
        return timer


def mean_over_seeds(rows: list[dict]) -> dict:
    import numpy as np

    keys = [k for k in rows[0] if k not in ("seed", "updates")]
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}


def probe_row(delay: int, result: dict) -> dict:
    t_star = result["alpha_at_t_star"]["mean"]
    return dict(delay=delay, steps=result["config"]["steps"],
                alpha_t_star=t_star, alpha_t_star_ci_low=result["alpha_at_t_star"]["ci95"][0],
                alpha_t_star_ci_high=result["alpha_at_t_star"]["ci95"][1],
                uniform=result["uniform"],
                alpha_t_star_over_uniform=t_star / result["uniform"],
                alpha_last_8=result["alpha_last_8"]["mean"],
                t_star_rank_1_share=result["t_star_rank_1_share"],
                reveal_mse=result["reveal_mse"],
                reveal_mse_predict_zero=result["reveal_mse_predict_zero"],
                reveal_error_over_predict_zero=result["reveal_mse"] / max(
                    result["reveal_mse_predict_zero"], 1e-12),
                reveal_reconstruction_mse=result["reveal_reconstruction_mse"],
                final_dyn_loss=result["final_dyn_loss"], train_seconds=result["train_seconds"])
