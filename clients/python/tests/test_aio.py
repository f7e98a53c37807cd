"""prac_client.aio against a real `prac serve`."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

import prac_client
from prac_client import aio
from conftest import Server
from test_client import check_commitment


async def test_aio_session_steps_plan_and_watch(server: Server) -> None:
    async with aio.Client(server.address, timeout=10) as client:
        (info,) = await client.policies()
        assert info.name == "pendulum"
        async with client.session("pendulum", epsilon_coef=0.000005, max_horizon=8) as session:
            obs = np.zeros(3, dtype=np.float32)
            prev = None
            for i in range(200):
                r = await session.step(obs)
                assert r.step == i
                check_commitment(prev, r, 8)
                prev = r
                obs = r.forecast_observations[0]
            plan = await session.plan()
            np.testing.assert_array_equal(plan.actions, prev.forecast_actions)

            updates = session.watch()
            current = await updates.__anext__()
            assert current.start_step == prev.step
            stepped = await session.step(obs)
            update = await asyncio.wait_for(updates.__anext__(), 5)
            assert update.start_step == stepped.step
            np.testing.assert_array_equal(update.actions, stepped.forecast_actions)
            await updates.aclose()
        with pytest.raises(prac_client.SessionNotFound, match="was closed"):
            await session.step(obs)
        other = await client.session("pendulum")
        with pytest.raises(prac_client.InvalidObservation):
            await other.step(np.zeros(2))
        # An error ends the stream, not the session.
        assert (await other.step(np.zeros(3))).step == 0
        assert await other.close() == 1


async def test_aio_errors(server: Server) -> None:
    async with aio.Client(server.address, timeout=10) as client:
        with pytest.raises(prac_client.PolicyNotFound):
            await client.session("nope")
        with pytest.raises(prac_client.InvalidOptions):
            await client.session("pendulum", max_horizon=100000)
        async with client.session("pendulum") as session:
            with pytest.raises(prac_client.InvalidObservation, match="finite"):
                await session.step([float("inf"), 0.0, 0.0])


async def test_aio_sessions_run_concurrently(server: Server) -> None:
    async with aio.Client(server.address, timeout=10) as client:

        async def run(seed: int) -> int:
            async with client.session("pendulum", seed=seed) as s:
                obs = np.zeros(3)
                for _ in range(50):
                    obs = (await s.step(obs)).forecast_observations[0]
                return (await s.plan()).start_step

        assert await asyncio.gather(*(run(k) for k in range(8))) == [49] * 8


async def test_aio_timeout_bounds_a_step(start_server) -> None:  # type: ignore[no-untyped-def]
    server: Server = start_server()
    async with aio.Client(server.address, timeout=0.5) as client:
        async with client.session("pendulum") as session:
            await session.step([0.0, 0.0, 0.0])
            server.pause()
            try:
                with pytest.raises(prac_client.DeadlineExceeded):
                    await session.step([0.0, 0.0, 0.0])
            finally:
                server.resume()
            assert (await session.step([0.0, 0.0, 0.0])).step >= 1
