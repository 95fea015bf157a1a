import tasks  # noqa
import json, os, sys, importlib.util
import numpy as np
spec = importlib.util.spec_from_file_location("bpv", "/tmp/exp/bp_variants_lib.py")
bpv = importlib.util.module_from_spec(spec); spec.loader.exec_module(bpv)
from benchmarks import metaworld_dynamics as md
mw = json.load(open("/tmp/exp/mw_button_20.json"))
for s in json.loads(sys.argv[1]):
    t = bpv.variant(**s)
    r = md.run_port(t, "button_press", 20, 0)
    tg = md.targets(r, mw)
    print(os.environ.get("SUPPORT"), json.dumps(s), "MJX ret %.1f±%.1f/%.1f ratio %.3f succ %.2f jmin %.4f/%.4f lag %.3f %s" % (
        r["return_mean"], r["return_std"], mw["return_mean"], tg["return_ratio"], r["success_last"],
        r["joint_min"], mw["joint_min"], tg["hand_mocap_ratio"], tg["targets_met"]), flush=True)
