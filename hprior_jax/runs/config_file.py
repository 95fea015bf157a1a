"""A run directory's config.json read back (resume, eval, export, grid): a file a hand edit
broke is named with the field and what it should hold, and a config.json that no longer
matches the configuration the run's newest checkpoint was written under is refused by field,
before anything is restored, moved or written."""
from __future__ import annotations

import json
from pathlib import Path

from hprior_jax.checkpoint import Checkpointer
from hprior_jax.config import CHANGEABLE_ON_RESUME, RunConfig, differing_fields, field_value
from hprior_jax.loop.run_files import latest_checkpoint_step
from hprior_jax.methods import registry

# set by a resume itself (a lowered budget keeps the buffer's size), not by a person
SET_BY_RESUME = ("out", "replay_capacity")


class ConfigFileError(ValueError):
    """A run's config.json cannot be used as it is; the message names the file and field."""


def read_json(run_dir: Path) -> dict:
    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: {run_dir} is not a run directory "
                                "written by `hprior train`")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ConfigFileError(f"{path} is not valid JSON ({e.msg}: line {e.lineno} column "
                              f"{e.colno}); repair it, or start a new run") from None
    if not isinstance(d, dict):
        raise ConfigFileError(f"{path} holds {type(d).__name__}, not an object of fields; "
                              "repair it, or start a new run")
    return d


def read_config(d: dict) -> RunConfig:
    """config.json of either format -> today's RunConfig."""
    d = {k: v for k, v in d.items() if k != "run_info"}
    if d.get("format", 1) == 1:
        d = registry.from_format_1(d)
    return RunConfig.from_dict(d)


def load_run_config(run_dir: Path) -> RunConfig:
    """The run's configuration from its config.json, checked against its newest checkpoint."""
    path = Path(run_dir) / "config.json"
    try:
        cfg = read_config(read_json(run_dir))
    except ConfigFileError:
        raise
    except (ValueError, TypeError, KeyError, AttributeError) as e:
        reason = str(e) if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"
        raise ConfigFileError(f"{path}: {reason}; repair it, or start a new run") from None
    check_fits_checkpoint(Path(run_dir), cfg)
    return cfg


def check_fits_checkpoint(run_dir: Path, cfg: RunConfig) -> None:
    """Refuses `cfg` (the run's config.json) when it differs, in a field a resume may not
    change, from the configuration saved with the run's newest checkpoint. Checkpoints
    saved without one pass; restoring then compares the arrays themselves."""
    saved = _saved_config(run_dir)
    if saved is None:
        return
    then = _dataclass_or_none(saved)
    fields = [] if then is None else [k for k in differing_fields(then, cfg)
                                      if k not in CHANGEABLE_ON_RESUME + SET_BY_RESUME]
    if "algo" in fields:  # another method: its sections differ with it
        fields = ["algo"]
    if fields:
        values = ", ".join(f"{k} ({field_value(saved, k)!r} there, "
                           f"{field_value(cfg, k)!r} here)" for k in fields)
        raise ConfigFileError(
            f"{Path(run_dir) / 'config.json'} differs from the configuration its newest "
            f"checkpoint was written under: {values}. Put the checkpoint's values back in "
            "config.json to resume it, or start a new run (another --out) with the new ones")


def _saved_config(run_dir: Path) -> dict | None:
    step = latest_checkpoint_step(run_dir)
    if step is None:
        return None
    ckpt = Checkpointer(Path(run_dir) / "checkpoints")
    try:
        return ckpt.saved_metadata(step).get("config")
    except Exception:  # unreadable metadata: a damaged checkpoint, restoring sets it aside
        return None
    finally:
        ckpt.close()


def _dataclass_or_none(saved: dict) -> RunConfig | None:
    try:
        return read_config(saved)
    except (ValueError, TypeError, KeyError):
        return None
