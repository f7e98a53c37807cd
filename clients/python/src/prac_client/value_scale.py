"""Adds or replaces a bundle's value scale, V_pi(s0) and V_rand(s0), so that sessions can give
an eps coefficient (eps = coef x (V_pi - V_rand)).

    python -m prac_client.value_scale BUNDLE --env ENV_ID --sb3 MODEL[.zip] [--episodes 50] [--seed 0]
    python -m prac_client.value_scale BUNDLE --v-pi X --v-rand Y

Measured as `prac evaluate` and `prac train` measure it: the mean discounted return (the
bundle's gamma) of the deterministic policy over episodes seeded SEED.., and of uniformly random
actions over the same seeds. The bundle is rewritten atomically; its tensors are unchanged.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any, Callable

import numpy as np
import numpy.typing as npt
from safetensors import safe_open

from prac_client import vecnormalize
from prac_client.bundle import write_bundle
from prac_client.sb3 import gymnasium_id, sb3_policy, zip_path

Act = Callable[[npt.NDArray[np.float32]], npt.ArrayLike]


def discounted_return(env: Any, act: Act, gamma: float, seed: int) -> float:
    """The discounted return of one episode from `env.reset(seed=seed)`."""
    obs, _ = env.reset(seed=seed)
    total, discount = 0.0, 1.0
    while True:
        action = np.asarray(act(np.asarray(obs, dtype=np.float32)), dtype=env.action_space.dtype)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += discount * float(reward)
        discount *= gamma
        if terminated or truncated:
            return total


def measure(env: Any, act: Act, gamma: float, episodes: int, seed: int) -> tuple[float, float]:
    """(V_pi, V_rand): mean discounted returns of `act` and of uniform random actions."""
    if episodes < 1:
        raise ValueError(f"episodes is {episodes}; expected >= 1")
    v_pi = float(np.mean([discounted_return(env, act, gamma, seed + k) for k in range(episodes)]))
    env.action_space.seed(seed)
    random = [discounted_return(env, lambda _: env.action_space.sample(), gamma, seed + k) for k in range(episodes)]
    return v_pi, float(np.mean(random))


def read_bundle(path: str | os.PathLike[str]) -> tuple[dict[str, npt.NDArray[np.float32]], dict[str, Any]]:
    """A bundle's tensors and manifest."""
    with safe_open(os.fspath(path), framework="numpy") as f:
        metadata = f.metadata() or {}
        if "manifest" not in metadata:
            raise ValueError(f"{os.fspath(path)}: no manifest in its metadata: not a prac bundle")
        tensors = {name: f.get_tensor(name) for name in f.keys()}
    return tensors, json.loads(metadata["manifest"])


def set_value_scale(path: str | os.PathLike[str], v_pi: float, v_rand: float) -> dict[str, Any]:
    """Writes (v_pi, v_rand) into the bundle's manifest; returns the manifest."""
    if not (np.isfinite(v_pi) and np.isfinite(v_rand)):
        raise ValueError(f"V_pi = {v_pi}, V_rand = {v_rand}: both must be finite")
    if v_pi <= v_rand:
        raise ValueError(
            f"V_pi = {v_pi} is not above V_rand = {v_rand}: an eps coefficient would mean nothing; "
            "give sessions an absolute epsilon instead"
        )
    tensors, manifest = read_bundle(path)
    manifest["value_scale"] = {"v_pi": float(v_pi), "v_rand": float(v_rand)}
    write_bundle(path, tensors, manifest)
    return manifest


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m prac_client.value_scale", description=__doc__.split("\n")[0])
    parser.add_argument("bundle", help="the bundle to rewrite (NAME.safetensors)")
    parser.add_argument("--env", help="gymnasium environment id to measure on, e.g. Pendulum-v1")
    parser.add_argument("--sb3", help="the SB3 checkpoint the bundle was exported from")
    parser.add_argument("--vecnormalize", help="its VecNormalize file [default: vecnormalize.pkl found beside it]")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--v-pi", type=float)
    parser.add_argument("--v-rand", type=float)
    args = parser.parse_args(argv)
    given = args.v_pi is not None and args.v_rand is not None
    if given == bool(args.env or args.sb3) or (not given and not (args.env and args.sb3)):
        parser.error("give --v-pi and --v-rand, or --env and --sb3 to measure them")
    if given:
        v_pi, v_rand = args.v_pi, args.v_rand
    else:
        import gymnasium

        stats_file, stats = vecnormalize.for_checkpoint(zip_path(args.sb3), args.vecnormalize)
        if stats is not None and stats.norm_reward:
            raise SystemExit(f"{stats_file}: {vecnormalize.NORMALISED_REWARDS}")
        _, manifest = read_bundle(args.bundle)
        env = gymnasium.make(gymnasium_id(args.env))
        policy = sb3_policy(args.sb3, env, args.vecnormalize)
        v_pi, v_rand = measure(env, policy, manifest["gamma"], args.episodes, args.seed)
    try:
        set_value_scale(args.bundle, v_pi, v_rand)
    except ValueError as e:
        raise SystemExit(str(e)) from None
    print(json.dumps({"bundle": args.bundle, "v_pi": v_pi, "v_rand": v_rand}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
