"""Train a small policy on the batched env with a short, self-contained PyTorch PPO (issue 15).

The env (dynmesh_warp.envs.RideSurfaceEnv, backend "torch") keeps everything on the simulation
device: observations, rewards and flags are torch views of the Warp arrays, actions go back the
same way, so the whole loop stays on the GPU. Writes the return curve (JSON, and a PNG when
matplotlib is installed).

    python examples/train_ppo.py --envs 1024 --minutes 4 --out out/ppo

PyTorch is not among the project's extras (``.[all]``): install the build for your machine first.

PPO as in Schulman et al. 2017 with GAE (lambda 0.95), clipped ratio 0.2, a Gaussian policy with
a state-independent log std, separate actor and critic MLPs (64-64, tanh), Adam 3e-4.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

try:
    import torch
    import torch.nn as nn
except ImportError:  # not among the project's extras (its wheel depends on the machine's CUDA)
    sys.exit("examples/train_ppo.py needs PyTorch: install it for your machine (https://pytorch.org), "
             "e.g. python -m pip install torch")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dynmesh_warp.envs import RideSurfaceEnv  # noqa: E402


def mlp(n_in, n_out, hidden=64):
    return nn.Sequential(nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, hidden), nn.Tanh(),
                         nn.Linear(hidden, n_out))


class ActorCritic(nn.Module):
    def __init__(self, n_obs, n_act):
        super().__init__()
        self.actor = mlp(n_obs, n_act)
        self.critic = mlp(n_obs, 1)
        self.log_std = nn.Parameter(torch.full((n_act,), -0.5))

    def dist(self, obs):
        return torch.distributions.Normal(self.actor(obs), self.log_std.exp())

    def value(self, obs):
        return self.critic(obs).squeeze(-1)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--envs", type=int, default=1024)
    ap.add_argument("--scene", default=None, help="scene YAML (default: the built-in pulsing blob)")
    ap.add_argument("--minutes", type=float, default=4.0)
    ap.add_argument("--horizon", type=int, default=32, help="env steps per env per iteration")
    ap.add_argument("--epochs", type=int, default=4)
    ap.add_argument("--minibatches", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/ppo")
    a = ap.parse_args(argv)
    torch.manual_seed(a.seed)
    env = RideSurfaceEnv(num_envs=a.envs, scene=a.scene, backend="torch", seed=a.seed)
    obs, _ = env.reset(seed=a.seed)
    dev = obs.device
    E, H = env.num_envs, a.horizon
    net = ActorCritic(obs.shape[1], 2).to(dev)
    opt = torch.optim.Adam(net.parameters(), lr=3e-4)
    gamma, lam, clip = 0.99, 0.95, 0.2
    ep_ret = torch.zeros(E, device=dev)
    ep_len = torch.zeros(E, device=dev)
    curve = []
    t0 = time.perf_counter()
    it = 0
    obs = obs.clone()  # the env's tensors are views of its arrays, overwritten by the next step
    while time.perf_counter() - t0 < 60.0 * a.minutes:
        buf_o = torch.zeros((H, E, obs.shape[1]), device=dev)
        buf_a = torch.zeros((H, E, 2), device=dev)
        buf_lp = torch.zeros((H, E), device=dev)
        buf_r = torch.zeros((H, E), device=dev)
        buf_d = torch.zeros((H, E), device=dev)
        buf_v = torch.zeros((H, E), device=dev)
        env_r = torch.zeros((), device=dev)  # the env's rewards alone (buf_r adds the bootstrap values)
        finished = []
        with torch.no_grad():
            for t in range(H):
                d = net.dist(obs)
                act = d.sample()
                buf_o[t], buf_a[t], buf_lp[t], buf_v[t] = obs, act, d.log_prob(act).sum(-1), net.value(obs)
                nobs, r, term, trunc, info = env.step(act)
                done = (term | trunc).float()
                # a truncated episode did not end: bootstrap its last step from the value of its
                # final observation (same-step autoreset: obs is already the next episode's)
                boot = gamma * net.value(info["final_obs"]) * trunc.float() if bool(trunc.any()) else 0.0
                buf_r[t], buf_d[t] = r + boot, done
                env_r += r.sum()
                ep_ret += r
                ep_len += 1
                if bool(done.any()):
                    finished.append(ep_ret[done.bool()].clone())
                ep_ret *= 1.0 - done
                ep_len *= 1.0 - done
                obs = nobs.clone()
            last_v = net.value(obs)
            adv = torch.zeros((H, E), device=dev)
            gae = torch.zeros(E, device=dev)
            for t in reversed(range(H)):
                nv = last_v if t == H - 1 else buf_v[t + 1]
                nonterm = 1.0 - buf_d[t]
                delta = buf_r[t] + gamma * nv * nonterm - buf_v[t]
                gae = delta + gamma * lam * nonterm * gae
                adv[t] = gae
            ret = adv + buf_v
        bo, ba, blp = buf_o.reshape(H * E, -1), buf_a.reshape(H * E, -1), buf_lp.reshape(-1)
        badv, bret = adv.reshape(-1), ret.reshape(-1)
        badv = (badv - badv.mean()) / (badv.std() + 1e-8)
        n = H * E
        mb = n // a.minibatches
        for _ in range(a.epochs):
            perm = torch.randperm(n, device=dev)
            for k in range(a.minibatches):
                idx = perm[k * mb:(k + 1) * mb]
                d = net.dist(bo[idx])
                lp = d.log_prob(ba[idx]).sum(-1)
                ratio = (lp - blp[idx]).exp()
                pg = -torch.min(ratio * badv[idx], ratio.clamp(1 - clip, 1 + clip) * badv[idx]).mean()
                vf = 0.5 * (net.value(bo[idx]) - bret[idx]).pow(2).mean()
                loss = pg + 0.5 * vf - 0.001 * d.entropy().sum(-1).mean()
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(net.parameters(), 0.5)
                opt.step()
        it += 1
        rets = torch.cat(finished) if finished else torch.zeros(0, device=dev)
        row = {"iteration": it, "env_steps": it * H * E, "wall_s": time.perf_counter() - t0,
               "episodes": int(rets.numel()), "mean_return": float(rets.mean()) if rets.numel() else None,
               "mean_reward_per_step": float(env_r) / (H * E)}
        curve.append(row)
        if it % 10 == 1:
            print(f"it {it:4d}  env-steps {row['env_steps']:>12,}  {row['wall_s']:6.1f} s  "
                  f"reward/step {row['mean_reward_per_step']:.3f}  return {row['mean_return']}", flush=True)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    info = {"envs": E, "device": str(dev), "torch": torch.__version__, "horizon": H, "seed": a.seed,
            "gpu": torch.cuda.get_device_name(0) if dev.type == "cuda" else None, "curve": curve}
    (out / "ppo_curve.json").write_text(json.dumps(info, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        x = [c["env_steps"] for c in curve]
        y = [c["mean_reward_per_step"] for c in curve]
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.plot(x, y)
        ax.set_xlabel("env steps")
        ax.set_ylabel("mean reward per env step")
        ax.set_title(f"PPO on RideSurfaceEnv ({E} envs, {dev})")
        fig.tight_layout()
        fig.savefig(out / "ppo_curve.png", dpi=120)
    except ImportError:
        pass
    print(f"wrote {out / 'ppo_curve.json'}")


if __name__ == "__main__":
    main()
