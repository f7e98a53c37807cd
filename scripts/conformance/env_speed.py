"""Env steps per second from Python, one process, random actions: prac's robots as gymnasium
envs over dm_env_rpc (prac_client.envs, each with its own `prac env-serve`), one env and a
vector env of --num-envs in one world (`gymnasium.make_vec`), against PyBullet 3.2.7's own
Python envs, and the pendulum against gymnasium's (the protocol's own cost). Prints a markdown
table (docs/domains.md).

Usage: python scripts/conformance/env_speed.py [--seconds 10] [--domains hopper,...]
[--num-envs 32] (run by scripts/conformance/speed in the conformance venv, PRAC_BIN set).
"""

import argparse
import time

import gym
import gymnasium
import numpy as np
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)

import prac_client.envs  # noqa: F401  (registers prac/Hopper-v0 and the others)

PYBULLET = {
    "hopper": "HopperBulletEnv-v0",
    "walker": "Walker2DBulletEnv-v0",
    "cheetah": "HalfCheetahBulletEnv-v0",
    "ant": "AntBulletEnv-v0",
    "humanoid": "HumanoidBulletEnv-v0",
}
PRAC = {
    "hopper": "prac/Hopper-v0",
    "walker": "prac/Walker-v0",
    "cheetah": "prac/Cheetah-v0",
    "ant": "prac/Ant-v0",
    "humanoid": "prac/Humanoid-v0",
}


def steps_per_second(reset, step, action_space, seconds, rng):
    """Steps (resets included in the time, not counted as steps) over `seconds`."""
    low, high = action_space.low, action_space.high
    actions = rng.uniform(low, high, size=(4096,) + low.shape).astype(np.float32)
    reset()
    steps = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        if step(actions[steps % len(actions)]):
            reset()
        steps += 1
    return steps / (time.perf_counter() - start)


def pybullet_rate(name, seconds, rng):
    env = gym.make(PYBULLET[name])
    env.seed(0)

    def step(a):
        _, _, done, _ = env.step(a)
        return done

    rate = steps_per_second(env.reset, step, env.action_space, seconds, rng)
    env.close()
    return rate


def gymnasium_rate(env_id, seconds, rng):
    env = gymnasium.make(env_id)
    seeds = iter(range(1 << 30))

    def step(a):
        _, _, terminated, truncated, _ = env.step(a)
        return terminated or truncated

    rate = steps_per_second(lambda: env.reset(seed=next(seeds)), step, env.action_space, seconds, rng)
    env.close()
    return rate


def prac_rate(name, seconds, rng):
    return gymnasium_rate(PRAC[name], seconds, rng)


def vector_rate(env_id, num_envs, seconds, rng):
    """Env steps (num_envs per call) over `seconds`; the vector resets its envs itself."""
    env = gymnasium.make_vec(env_id, num_envs=num_envs)
    low, high = env.action_space.low, env.action_space.high
    actions = rng.uniform(low, high, size=(64,) + low.shape).astype(np.float32)
    env.reset(seed=0)
    calls = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        env.step(actions[calls % len(actions)])
        calls += 1
    rate = calls * num_envs / (time.perf_counter() - start)
    env.close()
    return rate


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--domains", default=",".join(PRAC))
    parser.add_argument("--num-envs", type=int, default=32)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    n = args.num_envs
    print(f"| robot | PyBullet 3.2.7 (Python env) steps/s | prac, one env | ratio | prac, vector of {n} | ratio |")
    print("|---|---:|---:|---:|---:|---:|")

    def row(name, theirs, ours, vector):
        print(f"| {name} | {theirs:,.0f} | {ours:,.0f} | {ours / theirs:.2f}x | {vector:,.0f} | {vector / theirs:.2f}x |", flush=True)

    for name in args.domains.split(","):
        ours = prac_rate(name, args.seconds, rng)
        vector = vector_rate(PRAC[name], n, args.seconds, rng)
        theirs = pybullet_rate(name, args.seconds, rng)
        row(name, theirs, ours, vector)
    # The protocol's own cost: a step of the pendulum costs next to nothing on either side.
    ours = gymnasium_rate("prac/Pendulum-v0", args.seconds, rng)
    vector = vector_rate("prac/Pendulum-v0", n, args.seconds, rng)
    theirs = gymnasium_rate("Pendulum-v1", args.seconds, rng)
    row("pendulum (gymnasium's Pendulum-v1, pure Python)", theirs, ours, vector)


if __name__ == "__main__":
    main()
