"""Records transitions (obs, action, next_obs) from a gymnasium environment, for `prac fit-model`.

    python -m prac_client.record --env Pendulum-v1 (--episodes 20 | --steps N) --out transitions.safetensors \\
        [--random-fraction F] [--action-noise SIGMA] \\
        (--server 127.0.0.1:50051 --policy pendulum [--epsilon-coef C] | --sb3 MODEL[.zip])

--sb3 plays an SB3 SAC, TD3 or DDPG checkpoint, loaded as rl-zoo's enjoy.py loads one (its
pickled schedules replaced and its spaces taken from the environment, so zips saved with gym
load under gymnasium), behind its VecNormalize statistics where it has them (vecnormalize.pkl
beside the zip as the rl-zoo keeps it, or --vecnormalize FILE); transitions keep raw
observations. gym's MuJoCo ids (Hopper-v3, ...) are played as gymnasium's v4 ports,
with a warning.

Exploration widens the data a dynamics model is fitted on: each step is randomised with
probability --random-fraction, taking a uniform random action, or with --action-noise SIGMA the
policy's action plus Gaussian noise of std SIGMA (in half action ranges), clipped to the bounds;
the other steps play the policy's own action.

Writes float32 arrays obs [N, obs_dim], action [N, act_dim] (as executed, in the environment's
units), next_obs [N, obs_dim], reward [N], done [N] (1 where the episode terminated) and
explore [N] (1 where the action was not the policy's own; `prac fit-model` reports its held-out
error on both kinds of rows).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import Any, Callable

import numpy as np
import numpy.typing as npt
from safetensors.numpy import save_file

from prac_client import Client
from prac_client.sb3 import gymnasium_id, load_sb3, sb3_policy

# The SB3 loaders are prac_client.sb3's, also importable from here.
__all__ = ["Exploration", "Policy", "gymnasium_id", "load_sb3", "main", "record", "sb3_policy"]

Policy = Callable[[npt.NDArray[np.float32], bool], npt.NDArray[np.float32]]


@dataclasses.dataclass
class Exploration:
    """What `record` plays besides the policy: each step is randomised with probability
    `random_fraction`, taking a uniform random action, or with `action_noise` > 0 the policy's
    action plus Gaussian noise of that std in units of half the action range, clipped to the
    bounds. The other steps play the policy's own action. Randomised rows are flagged in the
    `explore` column."""

    random_fraction: float = 0.0
    action_noise: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.random_fraction <= 1.0:
            raise ValueError(f"random fraction {self.random_fraction}; expected 0..1")
        if not (np.isfinite(self.action_noise) and self.action_noise >= 0.0):
            raise ValueError(f"action noise {self.action_noise}; expected a finite value >= 0")


def record(
    env: Any,
    act: Policy,
    episodes: int | None,
    *,
    seed: int = 0,
    steps: int | None = None,
    exploration: Exploration | None = None,
) -> dict[str, npt.NDArray[np.float32]]:
    """Plays `episodes` episodes, or episodes until `steps` transitions (the last one cut short);
    `act(obs, first_step)` chooses each action, `exploration` what is played instead."""
    if (episodes is None) == (steps is None):
        raise ValueError("give episodes or steps")
    exploration = exploration or Exploration()
    # Separate streams: which steps are randomised does not depend on how.
    chooser, noise_source = (np.random.default_rng(s) for s in np.random.SeedSequence(exploration.seed).spawn(2))
    env.action_space.seed(exploration.seed)
    low, high = (np.asarray(b, dtype=np.float32) for b in (env.action_space.low, env.action_space.high))
    columns: dict[str, list[Any]] = {k: [] for k in ("obs", "action", "next_obs", "reward", "done", "explore")}
    episode = 0
    while (steps is None and episode < (episodes or 0)) or (steps is not None and len(columns["obs"]) < steps):
        obs, _ = env.reset(seed=seed + episode)
        episode += 1
        first = True
        while steps is None or len(columns["obs"]) < steps:
            # The policy sees every state, so a served session's plan follows what was executed.
            action = np.asarray(act(np.asarray(obs, dtype=np.float32), first), dtype=np.float32)
            first = False
            explored = bool(chooser.random() < exploration.random_fraction)
            if explored and exploration.action_noise > 0.0:
                noise = noise_source.normal(0.0, exploration.action_noise, size=action.shape) * (high - low) / 2
                action = np.clip(action + noise, low, high).astype(np.float32)
            elif explored:
                action = np.asarray(env.action_space.sample(), dtype=np.float32)
            next_obs, reward, terminated, truncated, _ = env.step(action.astype(env.action_space.dtype))
            for key, value in zip(columns, (obs, action, next_obs, reward, float(terminated), float(explored))):
                columns[key].append(value)
            obs = next_obs
            if terminated or truncated:
                break
    return {k: np.asarray(v, dtype=np.float32) for k, v in columns.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m prac_client.record", description=__doc__.split("\n")[0])
    parser.add_argument("--env", required=True, help="gymnasium environment id, e.g. Pendulum-v1")
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--episodes", type=int, help="episodes to play [default: 10]")
    length.add_argument("--steps", type=int, help="transitions to record (the last episode cut short)")
    parser.add_argument(
        "--random-fraction", type=float, default=0.0, help="share of steps whose action is randomised [default: 0]"
    )
    parser.add_argument(
        "--action-noise",
        type=float,
        default=0.0,
        help="randomise by Gaussian noise of this std (in half action ranges) on the policy's action, "
        "not by uniform actions [default: 0]",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", required=True)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--server", help="a prac server address (with --policy)")
    source.add_argument("--sb3", help="an SB3 SAC, TD3 or DDPG checkpoint (.zip); needs stable-baselines3")
    parser.add_argument("--policy", help="the served policy's name")
    parser.add_argument(
        "--vecnormalize", help="the --sb3 agent's VecNormalize file [default: vecnormalize.pkl found beside it]"
    )
    tolerance = parser.add_mutually_exclusive_group()
    tolerance.add_argument("--epsilon", type=float, help="absolute tolerance [default: the server's, 0]")
    tolerance.add_argument("--epsilon-coef", type=float, help="tolerance as a coefficient (needs a value scale)")
    args = parser.parse_args(argv)
    if args.steps is None and args.episodes is None:
        args.episodes = 10
    try:
        exploration = Exploration(args.random_fraction, args.action_noise, args.seed)
    except ValueError as e:
        parser.error(str(e))
    what = {"episodes": args.episodes, "steps": args.steps, "seed": args.seed, "exploration": exploration}

    import gymnasium

    env = gymnasium.make(gymnasium_id(args.env))
    if args.server:
        if not args.policy:
            parser.error("--server needs --policy")
        client = Client(args.server)
        session = client.session(args.policy, epsilon=args.epsilon, epsilon_coef=args.epsilon_coef)

        forecasts: list[int] = []
        f_ts: list[int] = []

        def act(obs: npt.NDArray[np.float32], first: bool) -> npt.NDArray[np.float32]:
            result = session.step(obs, new_episode=first)
            forecasts.append(result.forecast_length)
            f_ts.append(result.f_t)
            return result.action

        data = record(env, act, **what)
        session.close()
        client.close()
        source_name = f"prac:{args.server}/{args.policy}"
        served = {"forecast_mean": float(np.mean(forecasts)), "f_t_mean": float(np.mean(f_ts))}
    else:
        policy = sb3_policy(args.sb3, env, args.vecnormalize)

        def act_sb3(obs: npt.NDArray[np.float32], first: bool) -> npt.NDArray[np.float32]:
            return policy(obs)

        data = record(env, act_sb3, **what)
        source_name = f"sb3:{args.sb3}"
        served = {}
    # An episode starts wherever a row does not continue the one before it.
    starts = [0, *(1 + np.flatnonzero(np.any(data["next_obs"][:-1] != data["obs"][1:], axis=1))), len(data["obs"])]
    returns = [float(data["reward"][a:b].sum()) for a, b in zip(starts[:-1], starts[1:])]
    if args.steps is not None and len(returns) > 1:
        returns.pop()  # the episode --steps cut short
    facts = {"episodes": len(starts) - 1, "seed": args.seed, "policy": source_name}
    facts.update({"random_fraction": args.random_fraction, "action_noise": args.action_noise})
    save_file(data, args.out, metadata={"env": args.env, **{k: str(v) for k, v in facts.items()}})
    # safetensors metadata holds strings; the printed summary keeps numbers as numbers.
    summary = {"out": args.out, "transitions": int(data["obs"].shape[0]), "env": args.env}
    summary.update({**facts, "exploratory": int(data["explore"].sum())})
    summary.update({"return_mean": float(np.mean(returns)), "return_std": float(np.std(returns)), **served})
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
