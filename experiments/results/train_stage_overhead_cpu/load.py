# Loading dataset C twice into one host table: "old" (per-dataset load_steps, then concatenated) or "new" (load_step_table).
import resource, sys, time
import numpy as np
from heisd_jax.harness import data
paths = ["/tmp/ovh/C", "/tmp/ovh/C"]
t0 = time.perf_counter()
if sys.argv[1] == "old":
    parts = [data.load_steps(p) for p in paths]
    host = data.StepTable(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("image", "proprio", "instruction", "action")))
    del parts
else:
    host = data.load_step_table([(p, None) for p in paths])
dt = time.perf_counter() - t0
print(sys.argv[1], f"{host.size} steps, {host.image.nbytes/1e9:.2f} GB of images: {dt:.2f} s, peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1e6:.2f} GB")
