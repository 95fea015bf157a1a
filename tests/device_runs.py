"""Toy PEBBLE runs on several CPU devices, for tests/test_devices.py.

Run in a process of its own, with `--xla_force_host_platform_device_count` in XLA_FLAGS (the
device count is fixed when jax starts):
    python -m tests.device_runs full    OUT DEVICES     a whole run on DEVICES devices
    python -m tests.device_runs cut     OUT DEVICES     the same run stopped after 3 chunks
    python -m tests.device_runs resume  OUT DEVICES     continue OUT on DEVICES devices
    python -m tests.device_runs grid    OUT DEVICES     GRID_TASKS x sac, 2 seeds, --estimate
With JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID set, `full` is one process
of a multi-process run (the command every host runs)."""
import sys

from tests.toy_task import ensure_registered

ensure_registered()

from hprior_jax import cli  # noqa: E402

# 4 seeds, a feedback round every 40 steps from step 40, evaluation every 40 steps
TOY = ["--task", "toy_point", "--algo", "pebble", "--preset", "smoke", "--num-seed-steps",
       "20", "--chunk-steps", "20", "--eval-every", "40", "--num-eval-episodes", "2",
       "--sac.hidden-dim", "16", "--sac.hidden-depth", "1", "--sac.batch-size", "8",
       "--steps", "120", "--checkpoint-every", "40", "--seeds", "1", "2", "3", "4",
       "--no-progress"]
STOP_AFTER_CHUNKS = 3  # step 60: between two checkpoints, after the first feedback round
GRID_TASKS, GRID_SEEDS = ("toy_point", "toy_scaled"), (1, 2)


def grid_overrides() -> dict:
    from hprior_jax.agents.sac import SACConfig

    return dict(steps=80, num_seed_steps=20, chunk_steps=20, eval_every=40,
                checkpoint_every=40, num_eval_episodes=2,
                sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8))


def main(mode: str, out: str, devices: str) -> int:
    if mode == "full":
        return cli.main(["train", *TOY, "--out", out, "--devices", devices])
    if mode == "grid":
        from hprior_jax.experiments.grid import run_grid

        run_grid(out, GRID_TASKS, ["sac"], GRID_SEEDS, "smoke", grid_overrides(),
                 progress=False, devices=int(devices), estimate=True)
        return 0
    if mode == "resume":
        return cli.main(["train", "--resume", out, "--devices", devices, "--no-progress"])
    assert mode == "cut", mode
    from unittest import mock

    from hprior_jax.loop import host

    real_run = host.run
    with mock.patch.object(host, "run", lambda *a, **kw: real_run(
            *a, **{**kw, "max_chunks": STOP_AFTER_CHUNKS})):
        return cli.main(["train", *TOY, "--out", out, "--devices", devices])


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
