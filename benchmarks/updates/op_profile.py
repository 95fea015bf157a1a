"""Where the time of one world-model update goes: XLA op time grouped by the JAX source op.

    python -m benchmarks.updates.op_profile [--sizes reduced paper] [--seeds 1] [--updates 2]
                                            [--top 30]

Runs the update program of `benchmarks.updates.world_model_update` once under `jax.profiler`,
reads the trace's per-op events, maps each XLA op (fusion) to the `op_name` metadata of the
compiled HLO (the JAX call that produced it: layer, einsum, dropout, ...) and sums the time per
source op, forward and backward apart, and per op class (`OP_CLASSES`: an op whose fused
computation holds a `dot` is a matmul, whatever its source). Op times of the two CPU threads
overlap, so the shares are of summed op time, not of wall time.
Writes benchmarks/results/updates/op_profile_world_model.csv (rows `level` = class, then source).
"""
from __future__ import annotations

import argparse
import collections
import gzip
import json
import re
import tempfile
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import machine, select_device, write_rows

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "op_profile_world_model.csv"
_HLO_NAME = re.compile(r"\s+(?:ROOT )?%?([\w.\-]+) = ")
_OP_NAME = re.compile(r'op_name="([^"]+)"')
_CALLS = re.compile(r"calls=%?([\w.\-]+)")
_RNG_OPS = ("rng_bit_generator", "threefry", "random_bits")


OP_CLASSES = (
    ("dropout bits", _RNG_OPS),
    ("dropout mask and scale", ("Dropout",)),
    ("layer scan: saving/loading activations", ("dynamic_update_slice", "dynamic_slice")),
    ("layer norm", ("norm1", "norm2", "LayerNorm")),
    ("relative position (encodings, shift)", ("sinusoid", "pos_proj", "bind,jnd->bnij", "self_attn/pad",
                                              "self_attn/concatenate", "self_attn/slice")),
    ("attention softmax and mask", ("self_attn",)),
    ("activations (SiLU)", ("silu",)),
    ("embeddings, head and loss", ("DynamicsModel", "ObservationModel")),
)


def op_class(op_name: str, is_matmul: bool) -> str:
    """The class of an XLA op from its source: the first of OP_CLASSES whose marker the op_name
    holds; outside the models' calls it is the optimizer (Adam, clipping) and the update's glue."""
    if is_matmul:
        return "matmuls"
    for name, markers in OP_CLASSES:
        if any(m in op_name for m in markers):
            return name
    return "optimizer and glue"


def source_of(op_name: str) -> tuple[str, str]:
    """('fwd' | 'bwd', short source) of an HLO op_name such as
    'jit(run)/.../transpose(jvp(DynamicsModel))/.../self_attn/bind,jnd->bnij/transpose'."""
    direction = "bwd" if "transpose(" in op_name else "fwd"
    if any(r in op_name for r in _RNG_OPS):
        return direction, "rng (dropout bits)"
    if "Dropout" in op_name:
        return direction, "dropout (apply mask)"
    parts = [p for p in op_name.split("/") if p not in ("closed_call", "body", "while")]
    return direction, "/".join(parts[-2:])


def op_sources(hlo_text: str) -> dict[str, str]:
    """XLA op name -> JAX op_name metadata, from a compiled module's text. A fusion that carries
    no metadata of its own (XLA's matmul fusions) takes that of its fused computation's root."""
    sources, computation_source, fusion_calls = {}, {}, {}
    computation = None
    for line in hlo_text.splitlines():
        if line.endswith("{") and not line.startswith(" "):  # a computation's header
            computation = line.split()[0].lstrip("%")
            continue
        name = _HLO_NAME.match(line)
        if not name:
            continue
        meta = _OP_NAME.search(line)
        if meta:
            sources[name.group(1)] = meta.group(1)
            if computation and (computation not in computation_source or "ROOT " in line):
                computation_source[computation] = meta.group(1)
        elif (called := _CALLS.search(line)):
            fusion_calls[name.group(1)] = called.group(1)
    for fusion, called in fusion_calls.items():
        if called in computation_source:
            sources[fusion] = computation_source[called]
    return sources


def matmul_ops(hlo_text: str) -> set[str]:
    """XLA ops that are a `dot` or a fusion whose computation holds one."""
    with_dot, ops, calls = set(), set(), {}
    computation = None
    for line in hlo_text.splitlines():
        if line.endswith("{") and not line.startswith(" "):
            computation = line.split()[0].lstrip("%")
            continue
        name = _HLO_NAME.match(line)
        if not name:
            continue
        if " dot(" in line or " convolution(" in line:
            ops.add(name.group(1))
            if computation:
                with_dot.add(computation)
        elif (called := _CALLS.search(line)):
            calls[name.group(1)] = called.group(1)
    return ops | {op for op, called in calls.items() if called in with_dot}


def op_times_us(trace_dir: str) -> collections.Counter:
    """Summed duration (µs) per event name of the profiler trace in trace_dir."""
    path = sorted(Path(trace_dir).rglob("*.trace.json.gz"))[-1]
    with gzip.open(path) as f:
        events = json.load(f)["traceEvents"]
    totals = collections.Counter()
    for event in events:
        if event.get("ph") == "X":
            totals[event["name"]] += event["dur"]
    return totals


def profile(size: str, n_seeds: int, n_updates: int, dropout_rng: str | None) -> list[dict]:
    """Rows per op class then per (pass, source) of one traced call of the update program."""
    import jax

    from benchmarks.updates.world_model_update import update_program

    fn, states, keys, cfg = update_program(size, n_seeds, n_updates, dropout_rng)
    compiled = fn.lower(states, keys).compile()
    jax.block_until_ready(compiled(states, keys))  # warm-up
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir)
        jax.block_until_ready(compiled(states, keys))
        jax.profiler.stop_trace()
        times = op_times_us(trace_dir)
    hlo = compiled.as_text()
    sources, matmuls = op_sources(hlo), matmul_ops(hlo)
    by_source, by_class = collections.Counter(), collections.Counter()
    for op, us in times.items():
        if op in sources or op in matmuls:
            source = sources.get(op, "")
            by_class[op_class(source, op in matmuls)] += us
            by_source[source_of(source) if source else ("-", "matmul without a source")] += us
        elif "fusion" in op:
            by_class["optimizer and glue"] += us
            by_source[("-", "other fusions without a source")] += us
        # other events (executor, waits, Python) are not XLA ops: left out
    total = sum(by_class.values())
    head = {"size": size, "seeds": n_seeds, "dropout_rng": cfg.dropout_rng}
    row = lambda level, d, s, us: {**head, "level": level, "pass": d, "source": s,
                                   "ms_per_update": round(us / 1e3 / n_updates, 3),
                                   "share": round(us / total, 4), "machine": machine()}
    print(f"{size}, {n_seeds} seed(s), dropout {cfg.dropout_rng}: summed XLA op time "
          f"{total / 1e3 / n_updates:.1f} ms per update")
    return ([row("class", "-", c, us) for c, us in by_class.most_common()]
            + [row("source", d, s, us) for (d, s), us in by_source.most_common()])


def main(argv=None) -> None:
    from hprior_jax.prior.world_model import DROPOUT_RNGS

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=["reduced", "paper"], choices=["reduced", "paper"])
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--updates", type=int, default=2, help="updates in the profiled call")
    p.add_argument("--dropout-rng", default=None, choices=DROPOUT_RNGS,
                   help="PRNG of the dropout masks (default: the config's)")
    p.add_argument("--top", type=int, default=30, help="source rows printed (all are written)")
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.seeds < 1 or args.updates < 1:
        p.error("--seeds and --updates must be >= 1")
    select_device(args.device)
    rows = []
    for size in args.sizes:
        size_rows = profile(size, args.seeds, args.updates, args.dropout_rng)
        for r in [r for r in size_rows if r["level"] == "class"] + [
                r for r in size_rows if r["level"] == "source"][:args.top]:
            print(f"{r['ms_per_update']:9.2f} ms {100 * r['share']:5.1f}%  {r['level']:6s} "
                  f"{r['pass']:3s}  {r['source']}")
        rows += size_rows
        write_rows(rows, args.out)


if __name__ == "__main__":
    main()
