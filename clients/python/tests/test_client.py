"""The synchronous client against a real `prac serve`."""

from __future__ import annotations

import numpy as np
import pytest

import prac_client
from prac_client import Client, StepResult
from conftest import Server


def check_commitment(prev: StepResult | None, r: StepResult, max_horizon: int) -> None:
    """The server kept exactly the old plan's actions after the executed one."""
    assert 1 <= r.forecast_length <= max_horizon
    assert r.forecast_actions.shape == (r.forecast_length, 1)
    assert r.forecast_observations.shape == (r.forecast_length, 3)
    np.testing.assert_array_equal(r.action, r.forecast_actions[0])
    assert r.f_t == r.step + 1 - r.decided_at[0]
    assert np.all((r.forecast_actions >= -2.0) & (r.forecast_actions <= 2.0))
    if prev is None or r.step == 0:
        assert r.kept == 0 and r.broke_at is None
        return
    np.testing.assert_array_equal(r.forecast_actions[: r.kept], prev.forecast_actions[1 : 1 + r.kept])
    np.testing.assert_array_equal(r.decided_at[: r.kept], prev.decided_at[1 : 1 + r.kept])
    assert np.all(r.decided_at[r.kept :] == r.step)
    if r.broke_at is not None:
        assert r.broke_at == r.kept


def test_policies(client: Client) -> None:
    (info,) = client.policies()
    assert (info.name, info.domain, info.obs_dim, info.act_dim) == ("pendulum", "pendulum", 3, 1)
    np.testing.assert_array_equal(info.action_low, [-2.0])
    np.testing.assert_array_equal(info.action_high, [2.0])
    assert info.gamma == pytest.approx(0.98)
    assert info.value_scale == prac_client.ValueScale(10.0, -10.0)
    assert info.content_hash.startswith("sha256:")
    # The forecast's time base: Pendulum-v1's 0.05 s per step.
    assert info.control_period == pytest.approx(0.05)
    assert client.policy("pendulum") == info
    with pytest.raises(prac_client.PolicyNotFound):
        client.policy("hopper")


def test_session_streams_steps_with_forecast_accounting(client: Client) -> None:
    rng = np.random.default_rng(0)
    with client.session("pendulum", epsilon_coef=0.000005, max_horizon=12) as session:
        assert len(session.id) == 32
        assert session.options.epsilon == pytest.approx(1e-4, rel=1e-5)
        assert (session.options.growth_mode, session.options.growth, session.options.max_horizon) == ("grow", 2, 12)
        obs = np.array([0.1, -0.2, 0.3], dtype=np.float32)
        prev = None
        breaks = holds = 0
        for i in range(300):
            r = session.step(obs) if i % 100 else session.reset(obs)
            assert r is not None
            assert (r.step, r.episode) == (i % 100, i // 100)
            check_commitment(prev, r, 12)
            breaks += r.broke_at is not None
            holds += r.broke_at is None and r.step > 0
            prev = r
            obs = np.clip(r.forecast_observations[0] + rng.uniform(-0.05, 0.05, 3), -3, 3)
        assert breaks > 0 and holds > 0
        plan = session.plan()
        assert (plan.start_step, plan.episode, len(plan)) == (prev.step, prev.episode, prev.forecast_length)
        np.testing.assert_array_equal(plan.actions, prev.forecast_actions)
        np.testing.assert_array_equal(plan.observations, prev.forecast_observations)
        # reset() without an observation marks the next step as a new episode.
        assert session.reset() is None
        r = session.step(obs)
        assert (r.step, r.episode) == (0, 3)
    with pytest.raises(prac_client.SessionNotFound, match="was closed"):
        session.step(obs)


def test_watch_follows_the_plan(client: Client) -> None:
    with client.session("pendulum", growth="fixed 4") as session:
        first = session.step([0.0, 0.0, 0.0])
        updates = session.watch()
        current = next(updates)
        np.testing.assert_array_equal(current.actions, first.forecast_actions)
        by_step = {first.step: first}
        obs = first.forecast_observations[0]
        for _ in range(5):
            r = session.step(obs)
            by_step[r.step] = r
            obs = r.forecast_observations[0]
        # A slow watcher may skip plans but always reaches the newest; each plan it sees is the
        # one that step committed.
        seen = 0
        for plan in updates:
            assert len(plan) == 4
            np.testing.assert_array_equal(plan.actions, by_step[plan.start_step].forecast_actions)
            seen += 1
            if plan.start_step == 5:
                break
        assert seen >= 1
        updates.close()


def test_sampled_sessions_repeat_with_their_seed(client: Client) -> None:
    def actions(seed: int) -> list[float]:
        with client.session("pendulum", epsilon=0.01, seed=seed) as s:
            obs = np.zeros(3, dtype=np.float32)
            out = []
            for _ in range(30):
                r = s.step(obs)
                out.append(float(r.action[0]))
                obs = r.forecast_observations[0]
            return out

    assert actions(3) == actions(3)
    assert actions(3) != actions(4)


def test_errors_are_exceptions_with_the_server_message(client: Client) -> None:
    with pytest.raises(prac_client.PolicyNotFound, match="unknown policy 'nope'"):
        client.session("nope")
    with pytest.raises(prac_client.InvalidOptions, match="epsilon is -1"):
        client.session("pendulum", epsilon=-1.0)
    with pytest.raises(ValueError):
        client.session("pendulum", epsilon=0.1, epsilon_coef=0.1)
    with client.session("pendulum") as session:
        ok = session.step([0.0, 0.0, 0.0])
        with pytest.raises(prac_client.InvalidObservation, match="obs_dim = 3"):
            session.step([0.0, 0.0])
        with pytest.raises(prac_client.InvalidObservation, match=r"observation\[1\] is NaN"):
            session.step([0.0, float("nan"), 0.0])
        # The session lost nothing: the episode goes on from where it was.
        assert session.step([0.0, 0.0, 0.0]).step == ok.step + 1
    err = prac_client.SessionNotFound("x")
    assert isinstance(err, prac_client.PracError)


def wait_for_a_free_slot(client: Client, seconds: float = 30.0) -> None:
    """Opens (and closes) a session as soon as the server's one slot is free: the session that
    held it has expired."""
    import time

    deadline = time.monotonic() + seconds
    while True:
        try:
            client.session("pendulum").close()
            return
        except prac_client.Overloaded:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def test_expired_and_overloaded(start_server) -> None:  # type: ignore[no-untyped-def]
    # A TTL far longer than the few calls between a step and the next open.
    server: Server = start_server("--session-ttl", "1s", "--max-sessions", "1")
    with Client(server.address, timeout=10) as client:
        session = client.session("pendulum")
        session.step([0.0, 0.0, 0.0])
        with pytest.raises(prac_client.Overloaded, match="maximum of 1 sessions"):
            client.session("pendulum")
        # Its slot is free again once it has expired.
        wait_for_a_free_slot(client)
        # With patience, an expired session is re-opened with its plan and goes on.
        resumed = session.step([0.0, 0.0, 0.0])
        assert (resumed.step, session.resumes) == (1, 1)
        session.close()
    with Client(server.address, timeout=10, patience=0) as client:
        session = client.session("pendulum")
        session.step([0.0, 0.0, 0.0])
        wait_for_a_free_slot(client)
        # Without patience, the client says so.
        with pytest.raises(prac_client.SessionExpired, match=r"expired at .* open a new one with client\.session\(\.\.\.\)"):
            session.step([0.0, 0.0, 0.0])


def test_unavailable_server_is_a_clear_error() -> None:
    with Client("127.0.0.1:1", timeout=2) as client:
        with pytest.raises(prac_client.ServerUnavailable):
            client.policies()


def test_tls_and_token_configure_the_channel() -> None:
    # No server needed: a TLS channel to a plaintext port fails with UNAVAILABLE, not a crash.
    with Client("127.0.0.1:1", tls=prac_client.TlsConfig(), token="secret", timeout=1) as client:
        assert client._metadata == (("authorization", "Bearer secret"),)
        with pytest.raises(prac_client.ServerUnavailable):
            client.policies()


def test_timeout_bounds_a_streamed_step(start_server) -> None:  # type: ignore[no-untyped-def]
    server: Server = start_server()
    with Client(server.address, timeout=0.5) as client, client.session("pendulum") as session:
        session.step([0.0, 0.0, 0.0])
        server.pause()
        try:
            with pytest.raises(prac_client.DeadlineExceeded, match="0.5 s"):
                session.step([0.0, 0.0, 0.0])
        finally:
            server.resume()
        # A new stream carries on with the same session.
        assert session.step([0.0, 0.0, 0.0]).step >= 1
