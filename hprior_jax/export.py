"""A trained seed's learned reward and policy as a standalone folder, and their loaders.

    hprior export --run runs/cheetah_run_prior_... --seed 12345 --out cheetah_reward
    >>> reward = hprior_jax.load_reward("cheetah_reward")   # pure: (obs, action) -> r̂
    >>> policy = hprior_jax.load_policy("cheetah_reward")   # pure: obs -> action

The folder holds an orbax checkpoint of the parameters (`params/`) and `export.json` (task,
method, seed, step, the networks' configurations and what produced the run), so loading
needs neither the run directory nor its config."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp

from hprior_jax.agents.sac import SAC, SACConfig
from hprior_jax.networks.reward_ensemble import RewardConfig, mean_reward
from hprior_jax.runs.restore import restore_run
from hprior_jax.runs.run_dir import check_out_dir, run_info_of

FORMAT = 1


def export_seed(run_dir: Path, out: Path, seed: int | None = None,
                step: int | None = None) -> Path:
    out = check_out_dir(Path(out))
    restored = restore_run(run_dir, step)
    cfg, engine = restored.cfg, restored.engine
    seed = cfg.seeds[0] if seed is None else seed
    state = jax.device_get(restored.of_seed(seed))
    params = {"actor": state.sac.actor}
    reward_cfg = getattr(engine.method, "reward_cfg", None)  # methods with a learned reward
    if reward_cfg is not None:
        params["reward"] = state.method.reward
    meta = {"format": FORMAT, "task": cfg.task, "algo": cfg.algo, "seed": seed,
            "step": restored.step, "obs_size": engine.env.obs_size,
            "action_size": engine.env.action_size, "agent_config": dataclasses.asdict(cfg.sac),
            "reward_config": (dataclasses.asdict(reward_cfg) if reward_cfg is not None
                              else None),
            "run_dir": str(Path(run_dir).absolute()), "run_info": run_info_of(run_dir)}
    out.mkdir(parents=True, exist_ok=True)
    checkpointer = ocp.StandardCheckpointer()
    checkpointer.save((out / "params").absolute(), params)
    checkpointer.wait_until_finished()
    (out / "export.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out


def _read(path: Path) -> tuple[dict, dict]:
    path = Path(path)
    if not (path / "export.json").exists():
        raise FileNotFoundError(f"{path}/export.json not found: make the folder with "
                                "`hprior export --run RUN_DIR --out FOLDER`")
    meta = json.loads((path / "export.json").read_text())
    params = ocp.StandardCheckpointer().restore((path / "params").absolute())
    return meta, jax.tree.map(np.asarray, params)


def load_reward(path: Path):
    """The exported reward model as a pure function `(obs[..., obs], action[..., act]) ->
    r̂[...]`: the mean over the ensemble's members, the reward RL was trained on."""
    meta, params = _read(path)
    if meta["reward_config"] is None:
        raise ValueError(f"{path} is an export of a --algo {meta['algo']} run, which learns "
                         "no reward")
    cfg = RewardConfig(**{k: tuple(v) if isinstance(v, list) else v
                          for k, v in meta["reward_config"].items()})
    reward_params = params["reward"]

    def reward(obs, action):
        return mean_reward(reward_params, obs, action, cfg)

    return reward


def load_policy(path: Path):
    """The exported policy as a pure function `obs[..., obs] -> action[..., act]` (the
    deterministic action, tanh of the mean, as evaluation uses)."""
    meta, params = _read(path)
    sac = SAC(meta["obs_size"], meta["action_size"], SACConfig(**meta["agent_config"]))
    actor = params["actor"]

    def policy(obs):
        return sac.act(actor, obs, None, deterministic=True)

    return policy
