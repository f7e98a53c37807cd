"""Compares prac's planar walkers with PyBullet's from matched states: the cases that
matched_states.py recorded against what `prac play-from-states` played from them. Per domain and
number of steps played, the mean absolute difference of the torso's height, forward speed and
pitch, the joints' angles (as a fraction of their range) and the step's reward, next to how far
PyBullet's own values moved from the start state over those steps (the scale of the motion)."""

import json
import sys

import numpy as np

# Observation entries: z - initial z, 0.3 vx, pitch, then each joint's normalised angle and speed.
Z, VX, PITCH, JOINTS = 0, 3, 7, 8


def quantities(obs, joints):
    obs = np.asarray(obs, dtype=np.float64)
    return {
        "height (m)": obs[Z],
        "forward speed (m/s)": obs[VX] / 0.3,
        "pitch (rad)": obs[PITCH],
        # Normalised angles span 2 over a joint's range.
        "joint angle (range)": obs[JOINTS : JOINTS + 2 * joints : 2] / 2,
    }


def main():
    cases_path, ours_path = sys.argv[1], sys.argv[2]
    steps_shown = [1, 3, 10]
    with open(cases_path) as f:
        recorded = json.load(f)
    with open(ours_path) as f:
        ours = json.load(f)
    domain = recorded["domain"]
    joints = len(recorded["cases"][0]["state"]["joints"])
    rows = {}
    for case, played in zip(recorded["cases"], ours):
        theirs = case["pybullet"]
        start = quantities(theirs["start"], joints)
        mine_start = quantities(played["start"], joints)
        for name, value in start.items():
            rows.setdefault((0, name), ([], []))[0].append(np.abs(mine_start[name] - value).mean())
        for k in steps_shown:
            if len(theirs["steps"]) < k or len(played["steps"]) < k:
                continue
            a = quantities(theirs["steps"][k - 1]["obs"], joints)
            b = quantities(played["steps"][k - 1]["obs"], joints)
            for name in a:
                diff, motion = rows.setdefault((k, name), ([], []))
                diff.append(np.abs(b[name] - a[name]).mean())
                motion.append(np.abs(a[name] - start[name]).mean())
            diff, motion = rows.setdefault((k, "reward"), ([], []))
            diff.append(abs(played["steps"][k - 1]["reward"] - theirs["steps"][k - 1]["reward"]))
            motion.append(abs(theirs["steps"][k - 1]["reward"]))
    print(f"#### {domain}: {len(ours)} matched states\n")
    print("| steps | quantity | mean abs difference | PyBullet's own change (reward: its size) |")
    print("|---:|---|---:|---:|")
    for (k, name), (diff, motion) in sorted(rows.items(), key=lambda r: r[0][0]):
        scale = f"{np.mean(motion):.4f}" if motion else "-"
        print(f"| {k} | {name} | {np.mean(diff):.4f} | {scale} |")
    print()


if __name__ == "__main__":
    main()
