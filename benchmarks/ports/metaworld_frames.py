"""A contact sheet of what a person is shown of each MetaWorld task: `Env.render(i)` of envs 0
and 1 of one batch of 2 (two object placements) at reset. Not a speed benchmark: a look at
the frames, kept in docs/ports/metaworld.md.

    python -m benchmarks.ports.metaworld_frames --out docs/ports/metaworld_frames.jpg
"""
from __future__ import annotations

import argparse

import numpy as np

from hprior_jax import make_env
from tasks.metaworld.reference import ports


def task_frames(name: str, width: int, height: int) -> list[np.ndarray]:
    """Envs 0 and 1 of a batch of 2 of task `name`, just reset."""
    env = make_env(name, num_envs=2, seed=0)
    env.reset()
    return [env.render(i, width, height) for i in (0, 1)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="docs/ports/metaworld_frames.jpg")
    p.add_argument("--width", type=int, default=240)
    p.add_argument("--height", type=int, default=180)
    args = p.parse_args()
    import imageio.v3 as iio

    names = ports()
    rows = []
    for name in names:
        print(name, flush=True)
        rows.append(np.concatenate(task_frames(name, args.width, args.height), axis=1))
    sheet = np.concatenate(rows, axis=0)
    iio.imwrite(args.out, sheet)
    print(f"{args.out}: rows {', '.join(names)}; columns env 0, env 1 of one batch")


if __name__ == "__main__":
    main()
