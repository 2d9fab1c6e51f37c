"""The DDPG update of `lcrl bench learner`, in PyTorch eager: the reference
that lcrl's tch update is compared with, in one run on one machine.

Same sizes and settings as lcrl's defaults (docs/method.md Table I): a
global actor states -> 256 -> 256 -> actions (ReLU, tanh out), a critic
(states + actions) -> 256 -> 256 -> 1, Adam (actor 1e-3, critic 1e-2),
gamma 0.99, tau 1e-3, a minibatch drawn uniformly from a replay buffer of
random transitions, one critic step, one actor step and the soft update of
both targets per update.

Prints one line per thread count: THREADS MS_PER_UPDATE TORCH_VERSION.
"""

import argparse
import copy
import time

import torch
from torch import nn


def mlp(inputs, hidden, outputs):
    layers, width = [], inputs
    for h in hidden:
        layers += [nn.Linear(width, h), nn.ReLU()]
        width = h
    layers.append(nn.Linear(width, outputs))
    return nn.Sequential(*layers)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", default="1", help="comma-separated intra-op thread counts")
    p.add_argument("--updates", type=int, default=300)
    p.add_argument("--states", type=int, default=12)
    p.add_argument("--actions", type=int, default=6)
    p.add_argument("--batch", type=int, default=256)
    args = p.parse_args()
    device = torch.device(args.device)
    m, n, batch = args.states, args.actions, args.batch
    gamma, tau = 0.99, 1e-3
    for threads in [int(t) for t in args.threads.split(",")]:
        torch.set_num_threads(threads)
        torch.manual_seed(0)
        actor = nn.Sequential(mlp(m, [256, 256], n), nn.Tanh()).to(device)
        critic = mlp(m + n, [256, 256], 1).to(device)
        actor_target, critic_target = copy.deepcopy(actor), copy.deepcopy(critic)
        actor_opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
        critic_opt = torch.optim.Adam(critic.parameters(), lr=1e-2)
        size = 10_000
        buffer = {
            "obs": torch.rand(size, m, device=device) * 2 - 1,
            "action": torch.rand(size, n, device=device) * 2 - 1,
            "reward": -torch.ones(size, 1, device=device),
            "next_obs": torch.rand(size, m, device=device) * 2 - 1,
            "done": torch.zeros(size, 1, device=device),
        }
        pairs = [(t, s) for a, b in ((actor_target, actor), (critic_target, critic)) for t, s in zip(a.parameters(), b.parameters())]

        def update():
            idx = torch.randint(0, size, (batch,), device=device)
            obs, action, reward, next_obs, done = (buffer[k][idx] for k in ("obs", "action", "reward", "next_obs", "done"))
            with torch.no_grad():
                y = reward + gamma * (1 - done) * critic_target(torch.cat([next_obs, actor_target(next_obs)], 1))
            critic_loss = (critic(torch.cat([obs, action], 1)) - y).square().mean()
            critic_opt.zero_grad()
            critic_loss.backward()
            critic_opt.step()
            actor_loss = -critic(torch.cat([obs, actor(obs)], 1)).mean()
            actor_opt.zero_grad()
            actor_loss.backward()
            actor_opt.step()
            with torch.no_grad():
                for t, s in pairs:
                    t.mul_(1 - tau).add_(s, alpha=tau)

        def sync():
            if device.type == "cuda":
                torch.cuda.synchronize()

        for _ in range(10):
            update()
        sync()
        started = time.perf_counter()
        for _ in range(args.updates):
            update()
        sync()
        ms = (time.perf_counter() - started) / args.updates * 1e3
        print(f"{threads} {ms:.4f} {torch.__version__}", flush=True)


if __name__ == "__main__":
    main()
