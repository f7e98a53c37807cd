"""Compares `prac bench-domains --json` with pybullet_side.py's statistics: a markdown table per
statistic, and whether each mean agrees (within 10 % of PyBullet's, or within two standard errors
of the difference)."""

import json
import math
import sys


def agrees(ours_mean, ours_std, theirs_mean, theirs_std, n_ours, n_theirs):
    if abs(ours_mean - theirs_mean) <= 0.1 * abs(theirs_mean):
        return True
    se = math.sqrt(ours_std**2 / n_ours + theirs_std**2 / n_theirs)
    return abs(ours_mean - theirs_mean) <= 2 * se


def main():
    ours = {r["name"]: r for r in json.load(open(sys.argv[1]))}
    theirs = {r["name"]: r for r in json.load(open(sys.argv[2]))}
    names = [n for n in theirs if n in ours]
    print("| domain | statistic | prac | PyBullet 3.2.7 | agrees |")
    print("|---|---|---:|---:|---|")
    failures = 0
    for name in names:
        o, t = ours[name], theirs[name]
        n_o, n_t = o["episodes"], t["episodes"]
        rows = [
            ("return", o["mean_return"], o["std_return"], t["mean_return"], t["std_return"]),
            ("episode length", o["mean_length"], o["std_length"], t["mean_length"], t["std_length"]),
            (
                "torso distance (m)",
                o["mean_distance"] or 0.0,
                o["std_distance"] or 0.0,
                t["mean_torso_distance"],
                t["std_torso_distance"],
            ),
        ]
        for label, om, os_, tm, ts in rows:
            ok = agrees(om, os_, tm, ts, n_o, n_t)
            failures += not ok
            print(
                f"| {name} | {label} | {om:.2f} +- {os_ / math.sqrt(n_o):.2f} "
                f"| {tm:.2f} +- {ts / math.sqrt(n_t):.2f} | {'yes' if ok else 'no'} |"
            )
        print(f"| {name} | falls | {o['terminated']}/{n_o} | {t['terminated']}/{n_t} | |")
        for (term, ov), (_, tv) in zip(o["reward_terms"], t["reward_terms"]):
            print(f"| {name} | {term} per step | {ov:.3f} | {tv:.3f} | |")
    print()
    print(f"{failures} of {3 * len(names)} means disagree (+- is one standard error)")


if __name__ == "__main__":
    main()
