"""Random-policy statistics of PyBullet's original locomotion tasks (pybullet 3.2.7's
pybullet_envs), in the same shape as `prac bench-domains --json`: return, episode length, falls,
forward distance and each reward term's mean per step."""

import argparse
import json

import gym
import numpy as np
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)

ENVS = {
    "hopper": "HopperBulletEnv-v0",
    "walker": "Walker2DBulletEnv-v0",
    "cheetah": "HalfCheetahBulletEnv-v0",
    "ant": "AntBulletEnv-v0",
    "humanoid": "HumanoidBulletEnv-v0",
}
TERMS = ["alive", "progress", "electricity", "joints_at_limit"]


def mean_std(values):
    values = np.asarray(values, dtype=np.float64)
    return float(values.mean()), float(values.std())


def domain_stats(name, episodes, seed, gamma):
    env = gym.make(ENVS[name])
    robot = env.unwrapped.robot
    rng = np.random.default_rng(seed)
    returns, discounted, lengths, parts_x, torso_x = [], [], [], [], []
    terminated = 0
    term_sums = np.zeros(len(TERMS))
    for episode in range(episodes):
        env.seed(seed + episode)
        env.reset()
        start_parts, start_torso = robot.body_xyz[0], robot.body_real_xyz[0]
        total, disc, weight, steps, done = 0.0, 0.0, 1.0, 0, False
        while not done:
            action = rng.uniform(-1.0, 1.0, size=env.action_space.shape)
            _, reward, done, _ = env.step(action)
            # PyBullet's rewards list: alive, progress, electricity, joints at limit, feet
            # collision (always 0).
            term_sums += np.asarray(env.unwrapped.rewards[: len(TERMS)], dtype=np.float64)
            total += reward
            disc += weight * reward
            weight *= gamma
            steps += 1
        # Ended by the task, not the time limit (PyBullet's HalfCheetah never ends by itself).
        terminated += int(steps < env._max_episode_steps)
        returns.append(total)
        discounted.append(disc)
        lengths.append(steps)
        parts_x.append(robot.body_xyz[0] - start_parts)
        torso_x.append(robot.body_real_xyz[0] - start_torso)
    env.close()
    row = {"name": name, "episodes": episodes, "terminated": terminated}
    for key, values in [
        ("return", returns),
        ("discounted", discounted),
        ("length", lengths),
        ("distance", parts_x),
        ("torso_distance", torso_x),
    ]:
        row[f"mean_{key}"], row[f"std_{key}"] = mean_std(values)
    row["reward_terms"] = [[t, float(s / sum(lengths))] for t, s in zip(TERMS, term_sums)]
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--gamma", type=float, default=0.98)
    parser.add_argument("--domains", default=",".join(ENVS))
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    rows = [
        domain_stats(name, args.episodes, args.seed, args.gamma)
        for name in args.domains.split(",")
    ]
    with open(args.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
