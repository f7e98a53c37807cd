"""The 3D walkers (Ant, Humanoid) from matched start states: each episode of ours starts at a
fixed torso pose with random joint angles; PyBullet's reset is set to the same angles
(resetJointState, at rest) and both play the same actions, zero torques or uniform random ones,
for up to --steps steps (PyBullet's observations as its step returns them, the feet contacts
those of the step before, as ours). Prints, per step, the mean absolute difference of what they observe
and reward, next to PyBullet's own change from the start, and the mean signed pitch, height and
forward speed of each (which way they fall).

Usage: python scripts/conformance/from_reset.py [--domains ant,humanoid] [--cases 20]
[--steps 12] [--fixture FILE] (in the conformance venv, PRAC_BIN set; scripts/conformance/run
runs it). --fixture also writes each random case's seed, actions and PyBullet's observations
(tests/fixtures/pybullet-reset-steps.json, which the tests replay on ours).
"""

import argparse
import json

import gym
import numpy as np
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)

from matched_states import observe_now
from prac_client.envs import PracEnv

ENVS = {"ant": "AntBulletEnv-v0", "humanoid": "HumanoidBulletEnv-v0"}
# PyBullet's observation: z above the start, the target's sin and cos, 0.3 x velocity (x, y,
# z), roll, pitch, then each joint's normalised position and 0.1 x speed, then the feet.
HEIGHT, VX, ROLL, PITCH, JOINTS = 0, 3, 6, 7, 8
REPORT_STEPS = (1, 3, 6, 10)


def angles_from(obs, joints):
    """Joint angles from an observation's normalised positions and the joints' limits."""
    out = []
    for k, joint in enumerate(joints):
        low, high = joint.lowerLimit, joint.upperLimit
        out.append(0.5 * (low + high) + 0.5 * (high - low) * float(obs[JOINTS + 2 * k]))
    return out


def play(name, cases, steps, seed):
    ours = PracEnv(name)
    theirs = gym.make(ENVS[name])
    rng = np.random.default_rng(seed)
    rows = []  # per case and mode: (ours observations, theirs, our rewards, theirs, actions)
    for case in range(cases):
        for mode in ("zero", "random"):
            start, _ = ours.reset(seed=1000 + case)
            theirs.reset()
            robot, env = theirs.unwrapped.robot, theirs.unwrapped
            for joint, angle in zip(robot.ordered_joints, angles_from(start, robot.ordered_joints)):
                joint.reset_current_position(angle, 0.0)
            pybullet_start = observe_now(robot)
            env.potential = robot.calc_potential()
            ours_obs, theirs_obs, ours_r, theirs_r, actions = [start], [pybullet_start], [], [], []
            for _ in range(steps):
                action = np.zeros(theirs.action_space.shape) if mode == "zero" else rng.uniform(
                    -1.0, 1.0, size=theirs.action_space.shape
                )
                actions.append(action)
                o, r, terminated, truncated, _ = ours.step(action)
                to, tr, done, _ = theirs.step(action)
                ours_obs.append(o)
                theirs_obs.append(to)
                ours_r.append(r)
                theirs_r.append(tr)
                if terminated or truncated or done:
                    break
            rows.append((mode, np.array(ours_obs), np.array(theirs_obs), ours_r, theirs_r, actions, 1000 + case))
    ours.close()
    theirs.close()
    return rows


def report(name, rows):
    print(f"\n{name}: mean |ours - PyBullet| (PyBullet's own mean |change| from the start)\n")
    print("| actions | step | cases | height (m) | forward speed (m/s) | roll (rad) | pitch (rad) | joint position (normalised) | reward |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for mode in ("zero", "random"):
        for t in REPORT_STEPS:
            alive = [r for r in rows if r[0] == mode and len(r[1]) > t and len(r[2]) > t]
            if not alive:
                continue

            def diff(column, scale=1.0):
                d = np.mean([abs(o[t][column] - p[t][column]) for _, o, p, *_ in alive]) / scale
                own = np.mean([abs(p[t][column] - p[0][column]) for _, _, p, *_ in alive]) / scale
                return f"{d:.3g} ({own:.2g})"

            joints = np.mean([np.abs(o[t][JOINTS:-1:2] - p[t][JOINTS:-1:2]).mean() for _, o, p, *_ in alive])
            own_joints = np.mean([np.abs(p[t][JOINTS:-1:2] - p[0][JOINTS:-1:2]).mean() for _, _, p, *_ in alive])
            reward = np.mean([abs(ro[t - 1] - rt[t - 1]) for _, _, _, ro, rt, *_ in alive])
            size = np.mean([abs(rt[t - 1]) for _, _, _, _, rt, *_ in alive])
            print(
                f"| {mode} | {t} | {len(alive)} | {diff(HEIGHT)} | {diff(VX, 0.3)} | {diff(ROLL)} | {diff(PITCH)} "
                f"| {joints:.3g} ({own_joints:.2g}) | {reward:.3g} ({size:.2g}) |"
            )
    print("\nMean signed values (ours / PyBullet): which way they fall\n")
    print("| actions | step | height (m) | forward speed (m/s) | pitch (rad) |")
    print("|---|---:|---:|---:|---:|")
    for mode in ("zero", "random"):
        for t in REPORT_STEPS:
            alive = [r for r in rows if r[0] == mode and len(r[1]) > t and len(r[2]) > t]
            if not alive:
                continue

            def signed(column, scale=1.0):
                o = np.mean([x[1][t][column] for x in alive]) / scale
                p = np.mean([x[2][t][column] for x in alive]) / scale
                return f"{o:.3f} / {p:.3f}"

            print(f"| {mode} | {t} | {signed(HEIGHT)} | {signed(VX, 0.3)} | {signed(PITCH)} |")


def fixture_cases(rows, cases=5, steps=6):
    """The first random cases, for the tests: our reset seed, the actions, PyBullet's
    observations after each (float32-rounded lists)."""
    out = []
    for mode, _, theirs, _, _, actions, seed in rows:
        if mode != "random" or len(out) == cases or len(theirs) <= steps:
            continue
        out.append(
            {
                "seed": seed,
                "actions": [[round(float(x), 7) for x in a] for a in actions[:steps]],
                "observations": [[round(float(x), 7) for x in o] for o in theirs[1 : steps + 1]],
            }
        )
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--domains", default="ant,humanoid")
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fixture", help="also write the first random cases here (JSON)")
    args = parser.parse_args()
    fixture = {}
    for name in args.domains.split(","):
        rows = play(name, args.cases, args.steps, args.seed)
        report(name, rows)
        fixture[name] = fixture_cases(rows)
    if args.fixture:
        with open(args.fixture, "w") as f:
            json.dump(fixture, f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
