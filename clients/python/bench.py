"""Steps per second of one Python process against prac serve, sync and asyncio.

    cargo build --release && PRAC_BIN=../../target/release/prac python bench.py [--steps 3000]

Starts its own server with two random policies unless --server is given (then --policy names the
policy): "hopper-bench" (obs 15, act 3, actor and critics [256, 256], model 4 x 64), where the
server's Replan dominates, and "pendulum" (obs 3, act 1, [32, 32], model 2 x 16), where the
client's own cost shows. Sessions use eps coefficient 0.005.
"""

from __future__ import annotations

import argparse
import asyncio
import pathlib
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent / "tests"))

from prac_client import Client, aio  # noqa: E402
from prac_client.bundle import from_sb3_state_dict, random_model, random_sb3_state_dict, write_bundle  # noqa: E402


def hopper_bundle(directory: pathlib.Path) -> None:
    tensors, manifest = from_sb3_state_dict(
        random_sb3_state_dict(15, 3, [256, 256], seed=0),
        name="hopper-bench",
        domain="hopper",
        action_low=[-1.0] * 3,
        action_high=[1.0] * 3,
        gamma=0.98,
        value_scale=(10.0, -10.0),
        model=random_model(15, 3, [64, 64, 64, 64], seed=0),
    )
    write_bundle(directory / "hopper-bench.safetensors", tensors, manifest)


def observations(n: int, dim: int) -> np.ndarray:
    return np.random.default_rng(0).uniform(-1, 1, (n, dim)).astype(np.float32)


def bench_sync(address: str, policy: str, steps: int) -> float:
    with Client(address) as client, client.session(policy, epsilon_coef=0.005) as session:
        obs = observations(steps, session.policy.obs_dim)
        session.step(obs[0])
        start = time.perf_counter()
        for o in obs:
            session.step(o)
        return steps / (time.perf_counter() - start)


async def bench_aio(address: str, policy: str, steps: int, sessions: int) -> float:
    async with aio.Client(address) as client:
        obs = observations(steps, [p for p in await client.policies() if p.name == policy][0].obs_dim)

        async def run() -> None:
            async with client.session(policy, epsilon_coef=0.005) as session:
                for o in obs[: steps // sessions]:
                    await session.step(o)

        start = time.perf_counter()
        await asyncio.gather(*(run() for _ in range(sessions)))
        return (steps // sessions) * sessions / (time.perf_counter() - start)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server")
    parser.add_argument("--policy", action="append", help="policies to measure [default: both]")
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args()
    server = None
    address = args.server
    if address is None:
        from conftest import Server, write_toy_bundle

        directory = pathlib.Path(tempfile.mkdtemp())
        hopper_bundle(directory)
        write_toy_bundle(directory)
        server = Server(directory)
        address = server.address
    try:
        rows = []
        for policy in args.policy or ["hopper-bench", "pendulum"]:
            rows += [
                (policy, "sync, 1 session", bench_sync(address, policy, args.steps)),
                (policy, "aio, 1 session", asyncio.run(bench_aio(address, policy, args.steps, 1))),
                (policy, "aio, 8 sessions", asyncio.run(bench_aio(address, policy, args.steps, 8))),
            ]
    finally:
        if server is not None:
            server.stop()
    print(f"{'policy':<14}{'mode':<18}{'steps/s':>9}")
    for policy, mode, rate in rows:
        print(f"{policy:<14}{mode:<18}{rate:>9.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
