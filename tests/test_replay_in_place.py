"""The replay buffer is updated in place: an env step costs the same at any capacity.

Structural, not timed: the optimized program of a training chunk must not copy, select over
or otherwise rebuild a buffer-sized array; the only ops that produce one are the in-place
inserts (dynamic-update-slice) and the loop/branch plumbing that passes it through. A copy
per step made a 1M-row run 4-20x slower than a 20k-row one (benchmarks/runs/replay_capacity.py).
"""
import re

import pytest

from hprior_jax import presets
from hprior_jax.runs.build import build_engine
from hprior_jax.agents.sac import SACConfig

SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2)
# ops that pass a buffer through without touching its contents
PLUMBING = {"parameter", "get-tuple-element", "tuple", "while", "conditional", "bitcast"}
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%(\S+) = (\([^=]*?\)|\S+) ([a-z-]+)\(")


def buffer_sized_ops(hlo_text: str, capacity: int) -> list[str]:
    """Instructions whose result holds a [*, capacity, ...] array and that are neither
    plumbing nor an in-place dynamic-update-slice (fused or not)."""
    dim = re.compile(rf"\[(?:\d+,)*{capacity}[,\]]")
    bad = []
    for line in hlo_text.splitlines():
        m = _INSTRUCTION.match(line)
        if not m or not dim.search(m.group(2)):
            continue
        name, _, op = m.groups()
        in_place = op == "dynamic-update-slice" or (
            op == "fusion" and name.split(".")[0].endswith("dynamic-update-slice_fusion"))
        if op not in PLUMBING and not in_place:
            bad.append(line.strip()[:200])
    return bad


@pytest.mark.parametrize("algo, sizes", [
    ("sac", dict(replay_capacity=4099)),  # a size no other array in the toy program has
    ("pebble", dict(steps=20 * 4099)),  # PbRL buffers hold every step (whole 20-step episodes)
])
def test_chunk_updates_the_replay_buffer_in_place(algo, sizes):
    engine = build_engine(presets.train_preset("toy_point", algo, "smoke", **SMALL, **sizes))
    cap = engine.cfg.capacity
    rs = engine.init_seeds([1, 2])
    hlo = engine.compiled_chunk(rs, engine.cfg.num_seed_steps, 10).as_text()
    assert re.search(rf"\[2,{cap},2\]", hlo), "the buffer must be in the program"
    assert buffer_sized_ops(hlo, cap) == []
