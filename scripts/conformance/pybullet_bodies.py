"""The robots as PyBullet 3.2.7 simulates them (its MJCF importer's multibodies, read back with
getJointInfo / getDynamicsInfo / getLinkState with every joint at 0): per link its parent, joint,
axis, limits, mass, centre of mass and inertia; the motors' torque per unit action (PyBullet's
power x power_coef, or the Humanoid's motor_power); and the task's parts, whose mean x and y is the body position the progress
reward measures. Writes the JSON fixture the domain tests compare prac's robots with."""

import argparse
import json

import gym
import pybullet as p
import pybullet_envs  # noqa: F401  (registers the Bullet environments with gym)

ENVS = {
    "hopper": "HopperBulletEnv-v0",
    "walker": "Walker2DBulletEnv-v0",
    "cheetah": "HalfCheetahBulletEnv-v0",
    "ant": "AntBulletEnv-v0",
    "humanoid": "HumanoidBulletEnv-v0",
}
JOINT_TYPES = {p.JOINT_REVOLUTE: "hinge", p.JOINT_PRISMATIC: "slide", p.JOINT_FIXED: "fixed"}


def rounded(values, digits=6):
    return [round(float(v), digits) for v in values]


def robot_bodies(name):
    env = gym.make(ENVS[name])
    env.seed(0)
    env.reset()
    robot = env.unwrapped.robot
    client = robot._p._client
    body = robot.robot_body.bodies[robot.robot_body.bodyIndex]
    joints = p.getNumJoints(body, physicsClientId=client)
    for j in range(joints):
        p.resetJointState(body, j, 0.0, 0.0, physicsClientId=client)
    base = p.getDynamicsInfo(body, -1, physicsClientId=client)
    base_pos, _ = p.getBasePositionAndOrientation(body, physicsClientId=client)
    links = [
        {
            "name": p.getBodyInfo(body, physicsClientId=client)[0].decode(),
            "parent": None,
            "joint": None,
            "joint_type": "base",
            "mass": round(base[0], 6),
            "com": rounded(base_pos),
            "inertia": rounded(base[2]),
        }
    ]
    names = [links[0]["name"]]
    for j in range(joints):
        info = p.getJointInfo(body, j, physicsClientId=client)
        dyn = p.getDynamicsInfo(body, j, physicsClientId=client)
        state = p.getLinkState(body, j, computeForwardKinematics=1, physicsClientId=client)
        link = {
            "name": info[12].decode(),
            "parent": names[info[16] + 1],
            "joint": info[1].decode(),
            "joint_type": JOINT_TYPES[info[2]],
            "mass": round(dyn[0], 6),
            "com": rounded(state[0]),
            "inertia": rounded(dyn[2]),
        }
        if info[2] in (p.JOINT_REVOLUTE, p.JOINT_PRISMATIC):
            link["axis"] = rounded(info[13])
            link["anchor"] = rounded(state[4])
            if info[8] <= info[9]:
                link["range"] = rounded([info[8], info[9]])
        links.append(link)
        names.append(link["name"])
    if hasattr(robot, "motor_power"):
        # The Humanoid's apply_action: its own motor list and powers.
        pairs = zip(robot.motor_names, robot.motor_power)
    else:
        pairs = ((j.joint_name, j.power_coef) for j in robot.ordered_joints)
    motors = [{"joint": n, "torque": round(robot.power * c, 6)} for n, c in pairs]
    floor = p.getDynamicsInfo(0, -1, physicsClientId=client)[1]
    out = {
        "env": ENVS[name],
        "links": links,
        "motors": motors,
        "parts": list(robot.parts),
        "foot_list": list(robot.foot_list),
        "floor_friction": round(floor, 6),
    }
    env.close()
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    robots = {name: robot_bodies(name) for name in ENVS}
    with open(args.out, "w") as f:
        json.dump(robots, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
