"""Replan on board: the client's Replan on `prac export-onnx`'s files decides as the server does
on recorded trajectories, and a session with `fallback=` goes on on board through a lost server
or a silent link and back, as a robot needs it to."""

from __future__ import annotations

import asyncio
import json
import pathlib
import subprocess
import sys
from typing import Any, Iterator

import gymnasium as gym
import numpy as np
import pytest

import prac_client.envs  # noqa: F401  (registers prac/<Domain>-v0)
from prac_client import Client, FallbackFailed, aio
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client.onboard import Fallback
from prac_client.types import StepResult

from conftest import REPO, Server, prac_bin, write_toy_bundle

sys.path.insert(0, str(REPO / "clients" / "python"))
import fallback_proof  # noqa: E402

SHIPPED = sorted((REPO / "bundles").glob("*.safetensors"))
# Steps recorded per shipped bundle.
RECORDED_STEPS = 300


def export(bundle: pathlib.Path, out: pathlib.Path) -> pathlib.Path:
    subprocess.run([prac_bin(), "export-onnx", str(bundle), "--out", str(out)], check=True, stdout=subprocess.DEVNULL)
    return out


@pytest.fixture(scope="module")
def shipped_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    directory = tmp_path_factory.mktemp("shipped")
    for bundle in SHIPPED:
        (directory / bundle.name).symlink_to(bundle)
    server = Server(directory)
    yield server
    server.stop()


@pytest.mark.parametrize("bundle", SHIPPED, ids=lambda p: p.stem)
def test_on_board_replan_decides_as_the_server_on_recorded_trajectories(
    bundle: pathlib.Path, shipped_server: Server, tmp_path: pathlib.Path
) -> None:
    """Each step of a served episode replayed on board from the same held plan: the same kept,
    broke_at and f_t, and the same actions to float32 rounding, except at near-ties."""
    fallback = Fallback(export(bundle, tmp_path / "onnx"))
    env = gym.make(fallback_proof.ENV_IDS[bundle.stem])
    # (observation, the served answer, the plan it committed)
    recorded: list[tuple[np.ndarray, StepResult, pb.Plan]] = []
    with Client(shipped_server.address, timeout=10) as client:
        session = client.session(bundle.stem, epsilon_coef=0.005)
        options = session._resolved
        # The contract's names and units are the server's (ListPolicies), one per entry.
        info = session.policy
        features = fallback.networks.contract["features"]
        assert [(f.name, f.unit) for f in info.observation_features] == [(f["name"], f["unit"]) for f in features["observation"]]
        assert [(f.name, f.unit) for f in info.action_features] == [(f["name"], f["unit"]) for f in features["action"]]
        assert len(info.observation_features) == info.obs_dim and len(info.action_features) == info.act_dim
        observation, _ = env.reset(seed=3)
        for t in range(RECORDED_STEPS):
            result = session.step(observation, new_episode=t == 0)
            assert session._held is not None
            recorded.append((np.asarray(observation, dtype=np.float32), result, session._held))
            observation, _, terminated, truncated, _ = env.step(result.action)
            if terminated or truncated:
                break
        session.close()
    env.close()
    differ, now, forecast = 0, 0.0, 0.0
    for t, (observation, served, _) in enumerate(recorded):
        board = fallback.start(options, None if t == 0 else recorded[t - 1][2])
        local = board.step(observation.tolist(), t == 0)
        ours = (local.kept, local.broke_at if local.HasField("broke_at") else None, local.f_t)
        if ours != (served.kept, served.broke_at, served.f_t):
            differ += 1
            continue
        actions = np.array([a.action for a in local.forecast], dtype=np.float32)
        now = max(now, float(np.abs(actions[0] - served.action).max()))
        forecast = max(forecast, float(np.abs(actions - served.forecast_actions).max()))
    print(
        f"{bundle.stem}: {len(recorded)} steps, {differ} decided otherwise on board; largest action "
        f"difference {now:.1e} now, {forecast:.1e} over the forecast"
    )
    assert len(recorded) >= 100
    # Near-ties: the critics' values agree to float32 rounding (1.4e-5 relative), so a decision
    # differs only where Q(s, a) + eps and Q(s, pi(s)) are that close.
    assert differ <= max(1, len(recorded) // 100), f"{differ} of {len(recorded)} steps decided otherwise"
    # Later forecast entries come from the model rolled several steps, where rounding grows.
    assert now < 1e-4 and forecast < 1e-2, (now, forecast)


@pytest.mark.parametrize("cut", ["kill", "proxy"])
def test_the_hopper_runs_its_episode_on_board_through_a_lost_link(cut: str) -> None:
    """Every server SIGKILLed at step 100 and one back at 600 (or a proxy gone silent and back):
    no fall, the return within 2 % of the same episode uninterrupted, the steps contiguous, and
    the server's plan after the return continuing the local one."""
    ((reference, interrupted),) = fallback_proof.run("hopper", 1, cut, 100, 600, 0.005)
    print(f"{cut}: uninterrupted {reference.episode_return:.1f}, interrupted {interrupted.episode_return:.1f}, "
          f"{interrupted.local_steps} steps on board, kept after the return {interrupted.kept_after_return}")
    assert not reference.fell and not interrupted.fell
    assert interrupted.steps == reference.steps
    assert abs(interrupted.episode_return - reference.episode_return) <= 0.02 * abs(reference.episode_return)
    assert interrupted.contiguous
    # On board from step 100 until a server answered again, soon after step 600.
    assert 500 <= interrupted.local_steps <= 550, interrupted.local_steps
    assert interrupted.kept_after_return is not None and interrupted.kept_after_return >= 1
    assert interrupted.continues_local_plan


@pytest.fixture(scope="module")
def toy(tmp_path_factory: pytest.TempPathFactory) -> tuple[pathlib.Path, pathlib.Path]:
    """The toy bundle's folder and its export."""
    directory = tmp_path_factory.mktemp("toy")
    write_toy_bundle(directory)
    out = export(directory / "pendulum.safetensors", tmp_path_factory.mktemp("toy-onnx") / "onnx")
    return directory, out


def test_a_fallback_that_is_not_the_servers_bundle_is_refused_at_open(
    toy: tuple[pathlib.Path, pathlib.Path], tmp_path: pathlib.Path
) -> None:
    other = tmp_path / "other"
    other.mkdir()
    write_toy_bundle(other, seed=9)
    server = Server(other)
    try:
        with Client(server.address, timeout=10) as client:
            with pytest.raises(FallbackFailed, match="not the server's"):
                client.session("pendulum", epsilon=0.01, fallback=toy[1])
    finally:
        server.stop()


def test_a_sampled_session_cannot_fall_back(toy: tuple[pathlib.Path, pathlib.Path]) -> None:
    server = Server(toy[0])
    try:
        with Client(server.address, timeout=10) as client:
            with pytest.raises(FallbackFailed, match="deterministic"):
                client.session("pendulum", epsilon=0.01, seed=3, fallback=toy[1])
    finally:
        server.stop()


def test_a_fallback_folder_with_a_missing_or_changed_file_is_refused(
    toy: tuple[pathlib.Path, pathlib.Path], tmp_path: pathlib.Path
) -> None:
    import shutil

    missing = tmp_path / "missing"
    shutil.copytree(toy[1], missing)
    (missing / "model.onnx").unlink()
    with pytest.raises(FallbackFailed, match="model.onnx"):
        Fallback(missing)
    changed = tmp_path / "changed"
    shutil.copytree(toy[1], changed)
    data = bytearray((changed / "actor.onnx").read_bytes())
    data[-1] ^= 1
    (changed / "actor.onnx").write_bytes(bytes(data))
    with pytest.raises(FallbackFailed, match="not the file prac.json names"):
        Fallback(changed)
    shapes = tmp_path / "shapes"
    shutil.copytree(toy[1], shapes)
    contract: dict[str, Any] = json.loads((shapes / "prac.json").read_text())
    contract["observation"]["size"] += 1
    (shapes / "prac.json").write_text(json.dumps(contract))
    with pytest.raises(FallbackFailed, match="does not fit"):
        Fallback(shapes)
    with pytest.raises(FallbackFailed, match="prac.json"):
        Fallback(tmp_path / "nowhere")


def test_a_fallback_shared_by_sessions_keeps_each_ones_plan_apart(toy: tuple[pathlib.Path, pathlib.Path]) -> None:
    """A session that ended while local leaves nothing behind for the next one on the same
    fallback: that one starts served, at episode 0."""
    port = fallback_proof.free_port()
    address = f"127.0.0.1:{port}"
    server = fallback_proof.Server(toy[0], address)
    fallback = Fallback(toy[1])
    try:
        with Client(address, timeout=1, patience=0.05) as client:
            first = client.session("pendulum", epsilon=0.05, fallback=fallback)
            first.step([0.1, 0.2, 0.3], new_episode=True)
            server.kill()
            assert first.step([0.1, 0.2, 0.3]).local
            server = fallback_proof.Server(toy[0], address)
            second = client.session("pendulum", epsilon=0.05, fallback=fallback)
            result = second.step([0.1, 0.2, 0.3], new_episode=True)
            assert not result.local and (result.step, result.episode) == (0, 0)
    finally:
        server.stop()


def test_a_failing_fallback_is_an_error_that_carries_the_held_plans_action(toy: tuple[pathlib.Path, pathlib.Path]) -> None:
    server = Server(toy[0])
    fallback = Fallback(toy[1])

    def broken(*_: Any) -> Any:
        raise FallbackFailed("ONNX Runtime failed: test")

    try:
        with Client(server.address, timeout=2, patience=0.1) as client:
            session = client.session("pendulum", epsilon=1e9, growth="grow 2", max_horizon=12, fallback=fallback)
            first = session.step([0.1, 0.2, 0.3], new_episode=True)
            second = session.step([0.1, 0.2, 0.3])
            server.kill()
            fallback.networks.act = broken  # type: ignore[method-assign]
            with pytest.raises(FallbackFailed) as failed:
                session.step([0.1, 0.2, 0.3])
            held = failed.value.held
            assert held is not None and held.local and held.step == 2
            # The action the last answer committed for this step.
            np.testing.assert_array_equal(held.action, second.forecast_actions[1])
            assert first.step == 0
    finally:
        server.stop()


async def test_the_asyncio_client_goes_on_on_board_and_resumes(toy: tuple[pathlib.Path, pathlib.Path]) -> None:
    port = fallback_proof.free_port()
    address = f"127.0.0.1:{port}"
    server = fallback_proof.Server(toy[0], address)
    rng = np.random.default_rng(4)
    try:
        async with aio.Client(address, timeout=1, patience=0.1) as client:
            session = await client.session("pendulum", epsilon=0.05, max_horizon=12, fallback=toy[1])
            session.probe_every = 0.02
            where = []
            for t in range(60):
                if t == 20:
                    server.kill()
                if t == 40:
                    server = fallback_proof.Server(toy[0], address)
                result = await session.step(rng.uniform(-1, 1, 3), new_episode=t == 0)
                assert result.step == t
                where.append(result.local)
                await asyncio.sleep(0.01)
            assert where[:20] == [False] * 20 and where[20:40] == [True] * 20
            assert not where[-1] and session.resumes >= 1
            assert session.local_steps == sum(where)
            await session.close()
    finally:
        server.stop()


def test_the_docs_say_what_the_recorded_outage_runs_say() -> None:
    records = fallback_proof.recorded()
    assert {"hopper-kill", "hopper-proxy", "humanoid-kill", "humanoid-proxy"} <= set(records)
    text = fallback_proof.DOCS.read_text()
    assert fallback_proof.rewritten(text, records) == text, "run python clients/python/fallback_proof.py --docs"
    for record in records.values():
        summary = record["summary"]
        # What the runs must show: no more falls with the outage than without it, every step
        # contiguous, and the Hopper's returns within 2 %.
        assert summary["falls_interrupted"] <= summary["falls_uninterrupted"], record["command"]
        assert summary["all_contiguous"], record["command"]
        if "hopper" in record["command"]:
            assert summary["largest_return_difference"] <= 0.02, record["command"]


def test_the_docs_say_what_the_recorded_on_board_costs_say() -> None:
    import onboard_bench

    results = json.loads(onboard_bench.RESULTS.read_text())
    assert set(results["bundles"]) == {p.stem for p in SHIPPED}
    text = onboard_bench.DOCS.read_text()
    assert onboard_bench.rewritten(text, results) == text, "run python clients/python/onboard_bench.py --docs"
