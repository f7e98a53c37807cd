"""Markdown tables of the robots as PyBullet simulates them (the fixture
tests/fixtures/pybullet-bodies.json that pybullet_bodies.py writes): per link with mass, its mass,
centre of mass at rest and inertia; per motor, its joint's limits and torque per unit action."""

import json
import sys


def fmt(values, digits=3):
    return "(" + ", ".join(f"{v:.{digits}f}" for v in values) + ")"


def main():
    robots = json.load(open(sys.argv[1] if len(sys.argv) > 1 else "tests/fixtures/pybullet-bodies.json"))
    for name, robot in robots.items():
        links = robot["links"]
        total = sum(link["mass"] for link in links)
        print(f"**{name}** ({robot['env']}): {total:.2f} kg, {len(robot['parts'])} parts\n")
        print("| link | mass (kg) | centre at rest (m) | inertia (kg m^2) |")
        print("|---|---:|---|---|")
        for link in links:
            if link["mass"] > 0:
                print(f"| {link['name']} | {link['mass']:.3f} | {fmt(link['com'])} | {fmt(link['inertia'], 4)} |")
        print()
        print("| motor | limits (rad) | torque per unit action (N m) |")
        print("|---|---|---:|")
        by_joint = {link["joint"]: link for link in links}
        for motor in robot["motors"]:
            lo, hi = by_joint[motor["joint"]]["range"]
            print(f"| {motor['joint']} | {lo:.3f} .. {hi:.3f} | {motor['torque']:g} |")
        print()


if __name__ == "__main__":
    main()
