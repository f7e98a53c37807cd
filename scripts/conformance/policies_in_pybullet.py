"""Plays the bundles that `prac serve` serves in the PyBullet tasks their domains imitate
(pybullet 3.2.7's pybullet_envs): the policy trained on our physics, with PrAC off
(epsilon_coef 0, one action per step), controlling PyBullet's robot. Prints, per domain, the
return, episode length, falls and forward distance (PyBullet's body x, the mean over its parts)
as a markdown table; a policy that only works in our physics is a sign our physics is off.

  policies_in_pybullet.py --server 127.0.0.1:50181 [--episodes 20] [--domains hopper,...]
                          [--observe-current]

--observe-current gives the policy PyBullet's observation recomputed from the current link
poses and contacts (matched_states.observe_now) instead of the step's, whose torso pose and
speed are one substep old and feet contacts one step: to tell those lags from the physics when
a policy falls in PyBullet (prac's domains observe with the same lags).
"""

import argparse

import gym
import numpy as np
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)
from matched_states import observe_now
from prac_client import Client

ENVS = {
    "hopper": "HopperBulletEnv-v0",
    "walker": "Walker2DBulletEnv-v0",
    "cheetah": "HalfCheetahBulletEnv-v0",
    "ant": "AntBulletEnv-v0",
    "humanoid": "HumanoidBulletEnv-v0",
}
SEED = 777_000


def play(client, domain, episodes, observe_current=False):
    env = gym.make(ENVS[domain])
    returns, lengths, falls, distances = [], [], 0, []
    with client.session(domain, epsilon_coef=0.0) as session:
        for k in range(episodes):
            env.seed(SEED + k)
            obs = env.reset()
            robot = env.unwrapped.robot
            start_x = float(robot.body_xyz[0])
            reply = session.reset(obs)
            total, steps, done, info = 0.0, 0, False, {}
            while not done:
                obs, reward, done, info = env.step(np.asarray(reply.action))
                total += reward
                steps += 1
                if not done:
                    reply = session.step(observe_now(robot) if observe_current else obs)
            returns.append(total)
            lengths.append(steps)
            falls += int(not info.get("TimeLimit.truncated", False) and steps < 1000)
            distances.append(float(robot.body_xyz[0]) - start_x)
    env.close()
    return returns, lengths, falls, distances


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--server", default="127.0.0.1:50181")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--domains", default=",".join(ENVS))
    parser.add_argument("--observe-current", action="store_true")
    args = parser.parse_args()
    print(f"Seeds {SEED}+, {args.episodes} episodes, PrAC off.\n")
    print("| domain | PyBullet task | return | episode length | falls | forward (m) |")
    print("|---|---|---:|---:|---:|---:|")
    with Client(args.server, timeout=10) as client:
        for domain in args.domains.split(","):
            returns, lengths, falls, distances = play(client, domain, args.episodes, args.observe_current)
            print(
                f"| {domain} | {ENVS[domain]} | {np.mean(returns):.1f} +- {np.std(returns):.1f} "
                f"| {np.mean(lengths):.0f} | {falls}/{args.episodes} | {np.mean(distances):.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
