import envs, jax, jax.numpy as jnp, numpy as np
from envs import tasks as T, expert, rollout
from envs.env import TabletopEnv, EnvConfig
from heisd_jax import methods
tl = [t for t in T.get_tasks("object", None)][:2]
env = TabletopEnv(tl, EnvConfig(render=True))
pol = methods.make_policy("ar", env, checkpoint_path="/tmp/ck2/vla")
ex = expert.policy(env)
keys = env.initial_state_keys(np.arange(2), np.zeros(2, int), split="eval")
def run(k):
    st, ps, ak = rollout._start(env, pol, k, jnp.arange(2))
    es = ex.init(None, st)
    def body(c, t):
        st, es = c
        a, _, _ = pol.act(pol.params, st, (), ak)
        ea, es2, _ = ex.act(None, st, es, ak)
        obj = jax.vmap(env.object_pos)(st.data)
        return (jax.vmap(env.step)(st, a), es2), dict(a=a, ea=ea, tcp=st.kin.pos, obj=obj, phase=es.phase, succ=st.success)
    return jax.lax.scan(body, (st, es), jnp.arange(120))[1]
tr = jax.jit(run)(keys)
tr = jax.device_get(tr)
for i in range(0, 120, 6):
    print(i, "ph", tr["phase"][i, 0], "tcp", np.round(tr["tcp"][i, 0], 3), "obj", np.round(tr["obj"][i, 0, 0], 3), "\n   a ", np.round(tr["a"][i, 0], 2), "\n   ea", np.round(tr["ea"][i, 0], 2))
