"""Reference cases: what PyBullet (pybullet_envs) does in three situations the tests check ours
against, measured here so that every PyBullet number the tests hold comes from this script.

  hopper_drop   HopperBulletEnv-v0 set to the root's slides at rest, falling at 0.5 m/s, joints
                at 0 and still; 8 steps of zero torque and the observations they return
  thigh_torque  HopperBulletEnv-v0 set to x 0, z 1.0 moving forward at 2.5 m/s, level, joints at
                -0.3, -0.3, 0 and still; one step of the thigh's full torque backwards
  ant_at_rest   AntBulletEnv-v0 from the resets of seeds 0..29 with zero torque until the episode
                ends: its length and whether it ended by termination (not the 1000-step limit)

A state is given as ours is (`PlanarState`): the root's x slide, z slide (from the pose at rest)
and pitch hinge and the actuated joints in PyBullet's order, positions and speeds as
getJointState gives them, no feet contacts. It is set after a reset with resetJointState, the
feet contacts cleared and the episode's potential recomputed, as scripts/conformance/from_reset.py
sets its joints.

Usage (in the conformance venv):
  PYTHONPATH=scripts/conformance .conformance-venv/bin/python \\
      scripts/conformance/reference_cases.py [--out tests/fixtures/pybullet-reference-cases.json]
"""

import argparse
import json
from importlib.metadata import version

import gym
import numpy as np
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)

from matched_states import joint_index, observe_now, read_state

HOPPER = "HopperBulletEnv-v0"
HOPPER_ROOT = ["ignore1", "ignore2", "ignore3"]  # x slide, z slide, pitch hinge


def set_state(env, state):
    """Puts the reset Hopper into `state` (see above) and returns what it observes there."""
    robot, e = env.unwrapped.robot, env.unwrapped
    p = robot._p
    body = robot.objects[0] if isinstance(robot.objects, tuple) else robot.objects
    for name, q, v in zip(HOPPER_ROOT, state["root"], state["root_velocity"]):
        p.resetJointState(body, joint_index(p, body, name), q, v)
    for joint, q, v in zip(robot.ordered_joints, state["joints"], state["joint_velocities"]):
        joint.reset_current_position(q, v)
    robot.feet_contact[:] = 0.0
    obs = observe_now(robot)
    e.potential = robot.calc_potential()
    return obs


def planar_case(state, action, steps):
    env = gym.make(HOPPER)
    env.seed(0)
    env.reset()
    set_state(env, state)
    assert np.allclose(
        [read_state(env)[k] for k in state], [state[k] for k in state], atol=1e-9
    ), read_state(env)
    observations = []
    for _ in range(steps):
        obs, _, _, _ = env.step(np.asarray(action, dtype=np.float64))
        observations.append([float(x) for x in obs])
    env.close()
    return observations


def hopper_drop():
    state = {
        "root": [0.0, 0.0, 0.0],
        "root_velocity": [0.0, -0.5, 0.0],
        "joints": [0.0, 0.0, 0.0],
        "joint_velocities": [0.0, 0.0, 0.0],
    }
    action = [0.0, 0.0, 0.0]
    observations = planar_case(state, action, 8)
    for step, obs in enumerate(observations, 1):
        print(f"hopper_drop step {step}: z {obs[0]:+.4f} foot contact {obs[-1]:.0f}", end="")
        print(f", vertical {obs[5] / 0.3:+.4f} foot angle {obs[12]:+.4f}" if step == 4 else "")
    return {"state": state, "action": action, "observations": observations}


def thigh_torque():
    state = {
        "root": [0.0, 1.0, 0.0],
        "root_velocity": [2.5, 0.0, 0.0],
        "joints": [-0.3, -0.3, 0.0],
        "joint_velocities": [0.0, 0.0, 0.0],
    }
    action = [-1.0, 0.0, 0.0]
    (obs,) = planar_case(state, action, 1)
    print(
        f"thigh_torque: forward {obs[3] / 0.3:+.4f} vertical {obs[5] / 0.3:+.4f} pitch {obs[7]:+.4f}"
    )
    return {"state": state, "action": action, "observation": obs}


def ant_at_rest(seeds=range(30)):
    env = gym.make("AntBulletEnv-v0")
    out = {"seeds": list(seeds), "steps": [], "terminated": []}
    for seed in seeds:
        env.seed(seed)
        env.reset()
        steps, done = 0, False
        while not done:
            _, _, done, info = env.step(np.zeros(env.action_space.shape))
            steps += 1
        out["steps"].append(steps)
        out["terminated"].append(not info.get("TimeLimit.truncated", False))
    env.close()
    print(f"ant_at_rest: steps {out['steps']}, terminated {sum(out['terminated'])} of {len(seeds)}")
    return out


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", default="tests/fixtures/pybullet-reference-cases.json")
    args = parser.parse_args()
    cases = {
        "generated_by": "scripts/conformance/reference_cases.py, pybullet " + version("pybullet"),
        "hopper_drop": hopper_drop(),
        "thigh_torque": thigh_torque(),
        "ant_at_rest": ant_at_rest(),
    }
    with open(args.out, "w") as f:
        json.dump(cases, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
