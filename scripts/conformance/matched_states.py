"""Matched states: records PyBullet's planar walkers (pybullet 3.2.7's pybullet_envs) in states
reached by random actions, with the actions that follow and what PyBullet observes and rewards
for them, so that `prac play-from-states` can play the same actions from the same states.

  --out FILE      one JSON file per domain, FILE with {domain} in its name: the states, the
                  actions, and after each of them PyBullet's observation as its step returns it
                  ("obs", its torso one substep old), the same of the current link poses
                  ("obs_now", see observe_now) and its reward terms
  --fixture FILE  a few states per domain with what PyBullet computes at them (observation,
                  body x, alive bonus, effort costs for a fixed action): the fixture of the tests
  --step-fixture FILE
                  a few states per domain, one random action each and what PyBullet observes
                  after it: the tests' fixture for one step of the physics
  --policy-server HOST:PORT
                  with --out: states the policy that `prac serve` serves there reaches in
                  PyBullet (PrAC off, up to 150 steps in), and its actions from them, instead of
                  random ones: the states a controller meets, not those of a flailing robot
"""

import argparse
import json

import gym
import numpy as np
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)

ENVS = {
    "hopper": "HopperBulletEnv-v0",
    "walker": "Walker2DBulletEnv-v0",
    "cheetah": "HalfCheetahBulletEnv-v0",
}
TERMS = ["alive", "progress", "electricity", "joints_at_limit"]
ROOT_JOINTS = ["ignorex", "ignorez", "ignorey"]


def joint_index(p, body, name):
    for j in range(p.getNumJoints(body)):
        if p.getJointInfo(body, j)[1].decode() == name:
            return j
    raise KeyError(name)


def read_state(env):
    """The root's slides and hinge and the actuated joints, as getJointState gives them, and the
    feet contacts its last step measured (its next observation shows them)."""
    robot = env.unwrapped.robot
    p = robot._p
    body = robot.objects[0] if isinstance(robot.objects, tuple) else robot.objects
    names = {"hopper": ["ignore1", "ignore2", "ignore3"]}.get(
        robot_name(env), ROOT_JOINTS
    )
    root = [p.getJointState(body, joint_index(p, body, n)) for n in names]
    joints = [p.getJointState(j.bodies[j.bodyIndex], j.jointIndex) for j in robot.ordered_joints]
    return {
        "root": [float(s[0]) for s in root],
        "root_velocity": [float(s[1]) for s in root],
        "joints": [float(s[0]) for s in joints],
        "joint_velocities": [float(s[1]) for s in joints],
        "feet_contact": [float(c) for c in robot.feet_contact],
    }


def robot_name(env):
    return next(k for k, v in ENVS.items() if v == env.spec.id)


def observe_now(robot):
    """PyBullet's observation of the current state. Its step observes the links' poses and
    speeds as getLinkState caches them, from before the last substep moved them (one substep,
    4.1 ms, behind the joints), and the feet contacts of the step before; this recomputes the
    poses by forward kinematics first, and after a step it shows the contacts that step
    measured."""
    client = robot._p
    cached = client.getLinkState

    def current(body, link, **kwargs):
        return cached(body, link, **{**kwargs, "computeForwardKinematics": 1})

    client.getLinkState = current
    try:
        return robot.calc_state()
    finally:
        del client.getLinkState


def at_state(env, obs, action):
    """What PyBullet computes at the current state: its observation (as its step returned it,
    and recomputed from the current link poses), body x, alive bonus, and the effort costs the
    given action would have."""
    robot = env.unwrapped.robot
    e = env.unwrapped
    now = observe_now(robot)
    alive = robot.alive_bonus(now[0] + robot.initial_z, robot.body_rpy[1])
    electricity = e.electricity_cost * float(np.abs(action * robot.joint_speeds).mean())
    electricity += e.stall_torque_cost * float(np.square(action).mean())
    return {
        "obs": [float(x) for x in now],
        "obs_as_stepped": [float(x) for x in obs],
        "body_x": float(robot.body_xyz[0]),
        "alive": float(alive),
        "electricity": electricity,
        "joints_at_limit": e.joints_at_limit_cost * float(robot.joints_at_limit),
    }


def record(name, cases, horizon, seed, fixture, session=None):
    """States reached by random actions, or by the served policy when a session is given (then
    the actions that follow are the policy's too, from PyBullet's observations)."""
    env = gym.make(ENVS[name])
    rng = np.random.default_rng(seed)
    out = []
    episode = 0

    def act(obs, first=False):
        if session is None:
            return rng.uniform(-1.0, 1.0, size=env.action_space.shape)
        reply = session.reset(obs) if first else session.step(obs)
        return np.asarray(reply.action)

    while len(out) < cases:
        env.seed(seed + episode)
        obs = env.reset()
        episode += 1
        prefix = int(rng.integers(5, 40 if session is None else 150))
        done = False
        for i in range(prefix):
            obs, _, done, _ = env.step(act(obs, first=i == 0))
            if done:
                break
        if done:
            continue
        state = read_state(env)
        if fixture:
            action = np.linspace(-0.9, 0.9, env.action_space.shape[0])
            out.append({"state": state, "action": action.tolist(), **at_state(env, obs, action)})
            continue
        robot = env.unwrapped.robot
        start = observe_now(robot)
        case = {"state": state, "actions": [], "pybullet": {"start": start.tolist(), "steps": []}}
        for _ in range(horizon):
            action = act(obs)
            obs, reward, done, _ = env.step(action)
            case["actions"].append(action.tolist())
            body_x = float(robot.body_xyz[0])  # as stepped: observe_now recomputes it
            case["pybullet"]["steps"].append(
                {
                    "obs": obs.tolist(),
                    "obs_now": observe_now(robot).tolist(),
                    "body_x": body_x,
                    "reward": float(reward),
                    "reward_terms": dict(zip(TERMS, map(float, env.unwrapped.rewards))),
                    "terminated": bool(done),
                }
            )
            if done:
                break
        out.append(case)
    env.close()
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--domains", default=",".join(ENVS))
    parser.add_argument("--cases", type=int, default=30)
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--policy-server", help="play the policy `prac serve` serves there (PrAC off), not random"
    )
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--out", help="cases file, with {domain} in its name")
    group.add_argument("--fixture", help="the tests' fixture")
    group.add_argument("--step-fixture", help="the tests' fixture of single steps")
    args = parser.parse_args()
    names = args.domains.split(",")
    if args.step_fixture:
        fixture = {n: record(n, args.cases, 1, args.seed, False) for n in names}
        with open(args.step_fixture, "w") as f:
            json.dump(fixture, f)
            f.write("\n")
        return
    if args.fixture:
        fixture = {n: record(n, args.cases, 0, args.seed, True) for n in names}
        with open(args.fixture, "w") as f:
            json.dump(fixture, f, indent=1)
            f.write("\n")
        return
    for n in names:
        if args.policy_server:
            from prac_client import Client

            with Client(args.policy_server, timeout=10) as client:
                with client.session(n, epsilon_coef=0.0) as session:
                    cases = record(n, args.cases, args.horizon, args.seed, False, session)
        else:
            cases = record(n, args.cases, args.horizon, args.seed, False)
        with open(args.out.format(domain=n), "w") as f:
            json.dump({"domain": n, "cases": cases}, f)


if __name__ == "__main__":
    main()
