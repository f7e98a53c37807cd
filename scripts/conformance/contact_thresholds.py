"""The distance within which PyBullet reports each observed foot link touching the floor.

Bullet keeps a contact point while two shapes are closer than the pair's contact breaking
threshold (0.02 times the smaller shape's angular motion disc), and pybullet_envs counts any
reported point as a contact, so a foot is observed touching from that distance above the floor.
For each robot and each link of its foot_list this lowers the reset robot until the link's
closest point is a given distance above the floor, runs collision detection, and bisects that
distance between reported and not reported. Prints JSON: robot -> {link: threshold in m}; the
values are those in src/domains (`Foot::new`).

Usage: PYTHONPATH=scripts/conformance python contact_thresholds.py [--domains hopper,walker,cheetah,ant,humanoid]
"""

import argparse
import json

import gym
from pybullet_side import ENVS


def reported_at(env, body, link, floor, gap):
    """Whether `link` is reported touching `floor` with its closest point `gap` above it."""
    env.reset()
    p = env.unwrapped.robot._p
    for _ in range(50):
        distance = min(c[8] for c in p.getClosestPoints(body, floor, 1.0, linkIndexA=link))
        if abs(distance - gap) < 1e-8:
            break
        position, orientation = p.getBasePositionAndOrientation(body)
        lowered = (position[0], position[1], position[2] - (distance - gap))
        p.resetBasePositionAndOrientation(body, lowered, orientation)
    p.performCollisionDetection()
    points = p.getContactPoints(bodyA=body, linkIndexA=link)
    return any(c[2] == floor for c in points)


def thresholds(name):
    env = gym.make(ENVS[name])
    env.reset()
    robot = env.unwrapped.robot
    p = robot._p
    floor = next(b for b in range(p.getNumBodies()) if p.getNumJoints(b) == 0)
    found = {}
    for foot in robot.foot_list:
        part = robot.parts[foot]
        body, link = part.bodies[part.bodyIndex], part.bodyPartIndex
        low, high = 0.0, 0.05
        for _ in range(30):
            middle = (low + high) / 2
            if reported_at(env, body, link, floor, middle):
                low = middle
            else:
                high = middle
        found[foot] = round(low, 6)
    env.close()
    return found


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--domains", default=",".join(ENVS))
    args = parser.parse_args()
    print(json.dumps({n: thresholds(n) for n in args.domains.split(",")}, indent=1))


if __name__ == "__main__":
    main()
