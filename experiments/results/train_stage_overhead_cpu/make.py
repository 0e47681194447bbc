# Synthetic demos datasets of a build's shapes (64x128 images): A (3,000 steps), B (2,000); with argument C, C (40,000).
import sys, numpy as np
from envs import demos
def make(path, n_ep, n, seed):
    rng = np.random.default_rng(seed)
    w = demos.DatasetWriter(path, {"image_size": 64, "views": 2}, overwrite=True)
    N = n_ep * n
    proprio = rng.normal(size=(N, 8)).astype(np.float32)
    steps = dict(image=rng.integers(0, 255, (N, 64, 128, 3), dtype=np.uint8), proprio=proprio,
                 action=np.tanh(proprio[:, :7]).astype(np.float32),
                 ee_vel=np.zeros((N, 3), np.float32), ee_ang_vel=np.zeros((N, 3), np.float32),
                 ee_acc=np.zeros((N, 3), np.float32), gripper_vel=np.zeros(N, np.float32))
    w.add_shard(steps, [dict(task="lift_blue_cylinder", instruction="pick up the blue cylinder and hold it up",
                             start=i * n, length=n, episode=i, success=True) for i in range(n_ep)])
    w.finalize()
import sys
if sys.argv[1:] == ["C"]:
    make("/tmp/ovh/C", 400, 100, 2); sys.exit()
make("/tmp/ovh/A", 30, 100, 0)
make("/tmp/ovh/B", 20, 100, 1)
