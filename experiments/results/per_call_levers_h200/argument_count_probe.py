import time, json, os, jax, jax.numpy as jnp, numpy as np
res = {}
for n in [1, 30, 100, 300, 700]:
    for big in [False, True]:
        shape = (4096, 1024) if big else (8,)
        xs = [jnp.full(shape, i, jnp.bfloat16) for i in range(n)]
        f = jax.jit(lambda xs, y: (y + sum(x[0, 0] if big else x[0] for x in xs).astype(jnp.float32)))
        y = jnp.zeros(())
        f(xs, y).block_until_ready()
        ts = []
        for _ in range(50):
            t = time.perf_counter(); y = f(xs, y); y.block_until_ready(); ts.append(time.perf_counter() - t)
        res[f"{n}{'_big' if big else ''}"] = float(np.median(ts) * 1e3)
        print(n, big, round(res[f"{n}{'_big' if big else ''}"], 3), "ms", flush=True)
        del xs
json.dump(res, open(os.environ.get("OUT", "/tmp") + "/argprobe.json", "w"))
