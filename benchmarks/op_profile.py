"""Where the time of one world-model update goes: XLA op time grouped by the JAX source op.

    python -m benchmarks.op_profile [--size reduced] [--seeds 1] [--updates 4] [--top 30]

Runs the update program of `benchmarks.world_model_update` once under `jax.profiler`, reads the
trace's per-op events, maps each XLA op (fusion) to the `op_name` metadata of the compiled HLO
(the JAX call that produced it: layer, einsum, dropout, ...) and sums the time per source op,
forward and backward apart. Dropout's random bits are one group (`rng`). Op times of the two
CPU threads overlap, so the shares are of summed op time, not of wall time.
Writes benchmarks/results/op_profile_world_model.csv.
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

RESULTS = Path(__file__).resolve().parent / "results" / "op_profile_world_model.csv"
_HLO_NAME = re.compile(r"\s+(?:ROOT )?%?([\w.\-]+) = ")
_OP_NAME = re.compile(r'op_name="([^"]+)"')
_CALLS = re.compile(r"calls=%?([\w.\-]+)")
_RNG_OPS = ("rng_bit_generator", "threefry", "random_bits")


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


def main(argv=None) -> None:
    from hprior_jax.prior.world_model import DROPOUT_RNGS

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", default="reduced", choices=["reduced", "paper"])
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--updates", type=int, default=4, help="updates in the profiled call")
    p.add_argument("--dropout-rng", default=None, choices=DROPOUT_RNGS,
                   help="PRNG of the dropout masks (default: the config's)")
    p.add_argument("--top", type=int, default=30)
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.seeds < 1 or args.updates < 1:
        p.error("--seeds and --updates must be >= 1")
    select_device(args.device)
    import jax

    from benchmarks.world_model_update import update_program

    fn, states, keys, cfg = update_program(args.size, args.seeds, args.updates, args.dropout_rng)
    compiled = fn.lower(states, keys).compile()
    jax.block_until_ready(compiled(states, keys))  # warm-up
    with tempfile.TemporaryDirectory() as trace_dir:
        jax.profiler.start_trace(trace_dir)
        jax.block_until_ready(compiled(states, keys))
        jax.profiler.stop_trace()
        times = op_times_us(trace_dir)
    sources = op_sources(compiled.as_text())
    by_source = collections.Counter()
    for op, us in times.items():
        if op in sources:
            by_source[source_of(sources[op])] += us
        elif op.startswith("ynn_fusion"):  # XLA's matmul fusions keep no op_name
            by_source[("-", "matmuls (XLA keeps no source for them)")] += us
        elif "fusion" in op:
            by_source[("-", "other fusions without a source")] += us
        # other events (executor, waits, Python) are not XLA ops: left out
    total = sum(by_source.values())
    rows = [{"size": args.size, "seeds": args.seeds, "dropout_rng": cfg.dropout_rng,
             "pass": d, "source": s, "ms_per_update": round(us / 1e3 / args.updates, 3),
             "share": round(us / total, 4), "machine": machine()}
            for (d, s), us in by_source.most_common()]
    print(f"{args.size}, {args.seeds} seed(s), dropout {cfg.dropout_rng}: summed XLA op time "
          f"{total / 1e3 / args.updates:.1f} ms per update")
    for r in rows[:args.top]:
        print(f"{r['ms_per_update']:8.2f} ms {100 * r['share']:5.1f}%  {r['pass']}  {r['source']}")
    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
