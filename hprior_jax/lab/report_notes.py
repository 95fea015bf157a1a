"""The paragraphs a lab's report shows first: whether the world model predicts (else its α is
not evidence) and what uniform credit can reach at best; also for a report merged from the
seed shards of one lab (`hprior reward-lab --first-seed`), read from the files beside each
shard's results.csv (diagnostics.csv, run_info.json)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np


def report_notes(diagnostics: list[dict], ceiling: dict | None,
                 segment_len: int | None) -> list[str]:
    """`diagnostics`: the world model's, one dict per seed (empty when no rule reads it);
    `ceiling`: `metrics.uniform_credit_ceiling` of the held-out episodes."""
    notes = []
    skill = [d["wm/skill_vs_persistence"] for d in diagnostics]
    if skill and np.mean(skill) <= 0:
        notes.append(f"**WARNING: the world model does not predict** (skill over persistence "
                     f"{_skill_text(skill)}). Its α diagnostics and the "
                     "rules that read it (prior, positional) are not evidence about what a "
                     "predicting world model's α would do." + _latent_note(diagnostics))
    elif skill:  # it predicts: say how well, a skill near 0 reads very differently from 0.3
        notes.append(f"World model: skill over persistence {_skill_text(skill)}"
                     + _alpha_note(diagnostics) + ".")
    if ceiling is not None and segment_len is not None:
        notes.append(f"Uniform credit's ceiling on the held-out episodes (the true reward "
                     f"against its own {segment_len}-step moving mean): Pearson "
                     f"{ceiling['pearson']:.3f}, within-episode Pearson "
                     f"{ceiling['episode_pearson']:.3f}.")
    return notes


def _skill_text(skill: list[float]) -> str:
    return (f"{np.mean(skill):+.3f}, mean of {len(skill)} seeds, "
            f"{sum(k > 0 for k in skill)} of them above 0")


def _mean(diagnostics: list[dict], key: str) -> float:
    return float(np.mean([d[key] for d in diagnostics]))


def _alpha_note(diagnostics: list[dict]) -> str:
    if "alpha/position_r2" not in diagnostics[0]:
        return ""
    return (f"; the share of its α's variance that step position explains (R²) is "
            f"{_mean(diagnostics, 'alpha/position_r2'):.2f}")


def _latent_note(diagnostics: list[dict]) -> str:
    """Where the decoded skill fails, whether the transformer predicts in its own latent space
    and how much of the decoded error the observation model's reconstruction alone makes."""
    if "wm/latent_skill_vs_persistence" not in diagnostics[0]:  # a cache of an older lab
        return ""
    return (f" In latent space its skill over persistence is "
            f"{_mean(diagnostics, 'wm/latent_skill_vs_persistence'):+.3f}; the observation "
            f"model's reconstruction error alone is "
            f"{_mean(diagnostics, 'wm/reconstruction_error'):.4g} against persistence's "
            f"{_mean(diagnostics, 'wm/persistence_error'):.4g}.")


def write_diagnostics(path: Path, diagnostics: list[dict]) -> None:
    names = [k for k in diagnostics[0] if k != "seed"]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["seed", *names], lineterminator="\n")
        writer.writeheader()
        writer.writerows(diagnostics)


def read_diagnostics(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return [{k: int(v) if k == "seed" else float(v) for k, v in row.items()}
                for row in csv.DictReader(f)]


def merged_notes(results_paths, out_dir: Path) -> list[str]:
    """The notes of labs merged into one report, from the files beside their results.csv.
    Diagnostics are merged only when every lab has them and no seed is in two labs (the seed
    shards of one lab; labs of different world models keep theirs apart), and written to
    OUT/diagnostics.csv; the ceiling is said only when every lab states the same one (the
    same held-out episodes); labs of different datasets (`Dataset.digest`) are warned of."""
    folders = [Path(p).parent for p in results_paths]
    diagnostics = []
    if all((f / "diagnostics.csv").exists() for f in folders):
        per_lab = [read_diagnostics(f / "diagnostics.csv") for f in folders]
        seeds = [d["seed"] for lab in per_lab for d in lab]
        if len(seeds) == len(set(seeds)):
            diagnostics = sorted((d for lab in per_lab for d in lab), key=lambda d: d["seed"])
            Path(out_dir).mkdir(parents=True, exist_ok=True)
            write_diagnostics(Path(out_dir) / "diagnostics.csv", diagnostics)
    infos = [json.loads((f / "run_info.json").read_text())
             for f in folders if (f / "run_info.json").exists()]
    ceilings = {json.dumps([i.get("uniform_credit_ceiling"), i.get("segment_len")])
                for i in infos}
    ceiling, segment_len = (json.loads(ceilings.pop()) if len(infos) == len(folders)
                            and len(ceilings) == 1 else (None, None))
    notes = report_notes(diagnostics, ceiling, segment_len)
    digests = sorted({i["dataset_digest"] for i in infos if "dataset_digest" in i})
    if len(digests) > 1:
        notes.insert(0, f"**WARNING: these labs learned from different datasets** (digests "
                        f"{', '.join(digests)}): their rows are not one lab's, and a paired "
                        "comparison across them mixes datasets.")
    return notes
