import tasks  # noqa
import json, sys, time, importlib.util
spec = importlib.util.spec_from_file_location("bpv", "/tmp/exp/bp_variants_lib.py")
bpv = importlib.util.module_from_spec(spec); spec.loader.exec_module(bpv)
from benchmarks.metaworld_throughput import mjx_rate
for s in json.loads(sys.argv[1]):
    t = bpv.variant(**s)
    print(json.dumps(s), mjx_rate(t, 64, 20, 3), flush=True)
