"""The Python baseline server (clients/python/baseline) answers as prac serve does: the same
actions (to float32 rounding) and the same kept, broke_at and f_t over a few hundred steps, so the
performance comparison in docs/performance.md compares like with like."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import numpy as np
import pytest

from prac_client import Client

from conftest import REPO, Server, write_toy_bundle


def test_the_baseline_answers_as_prac_serve_does(bundles: pathlib.Path, server: Server) -> None:
    answers_alike(bundles, server)


def test_the_baseline_answers_as_prac_serve_does_with_layer_norm_critics(tmp_path: pathlib.Path) -> None:
    write_toy_bundle(tmp_path, layer_norm=True)
    server = Server(tmp_path)
    try:
        answers_alike(tmp_path, server)
    finally:
        server.stop()


def test_the_baseline_keeps_forecasts_inside_the_observation_bounds_as_prac_serve_does(tmp_path: pathlib.Path) -> None:
    # Bounds tighter than the observations the test sends (within [-3, 3]), one side unbounded.
    write_toy_bundle(tmp_path, obs_bounds=([-0.5, -0.5, -float("inf")], [0.5, 0.5, 0.2]))
    server = Server(tmp_path)
    try:
        seen = answers_alike(tmp_path, server)
    finally:
        server.stop()
    assert seen.size > 0
    assert (seen[:, :2] >= -0.5).all() and (seen[:, :2] <= 0.5).all() and (seen[:, 2] <= 0.2).all()
    assert (seen[:, 2] < -0.5).any(), "the unbounded side was bounded"


def test_the_baseline_applies_a_bundles_default_guard_as_prac_serve_does(tmp_path: pathlib.Path) -> None:
    default_guard = {"every_critic": True, "support_limit": 0.5}
    write_toy_bundle(tmp_path, default_guard=default_guard)
    server = Server(tmp_path)
    try:
        with Client(server.address, timeout=10) as client:
            (info,) = client.policies()
            assert (info.default_guard.every_critic, info.default_guard.support_limit) == (True, 0.5)
            session = client.session("pendulum", epsilon=1e-4)
            assert (session.options.guard.every_critic, session.options.guard.support_limit) == (True, 0.5)
            session.close()
        # Sessions that set no guard get the default; the guarded ones must break plans.
        answers_alike(tmp_path, server, bundle_default=True)
    finally:
        server.stop()


def test_the_baseline_holds_eps_to_a_bundles_limit_as_prac_serve_does(tmp_path: pathlib.Path) -> None:
    # The toy bundle's V_pi - V_rand is 20: the limit 0.001 holds eps to 0.02.
    write_toy_bundle(tmp_path, default_guard={"support_limit": 0.5, "max_epsilon_coef": 0.001})
    server = Server(tmp_path)
    try:
        baseline, address = start_baseline(tmp_path)
        try:
            with Client(server.address, timeout=10) as ours, Client(address, timeout=10) as theirs:
                for client in (ours, theirs):
                    (info,) = client.policies()
                    assert info.default_guard.max_epsilon_coef == 0.001
                rng = np.random.default_rng(7)
                # Above the limit (held), below it (as asked), and the paper's test (no limit).
                for options, expected in (
                    ({"epsilon_coef": 0.01}, 0.02),
                    ({"epsilon": 1.0}, 0.02),
                    ({"epsilon": 0.005}, 0.005),
                    ({"epsilon": 1.0, "support_limit": 0.0}, 1.0),
                ):
                    a = ours.session("pendulum", growth="grow 2", max_horizon=12, **options)
                    b = theirs.session("pendulum", growth="grow 2", max_horizon=12, **options)
                    assert a.options.epsilon == b.options.epsilon == pytest.approx(expected, rel=1e-6), options
                    assert a.options.guard == b.options.guard, options
                    obs = rng.uniform(-1, 1, 3)
                    for t in range(60):
                        ra, rb = a.step(obs, new_episode=t == 0), b.step(obs, new_episode=t == 0)
                        np.testing.assert_allclose(ra.forecast_actions, rb.forecast_actions, atol=1e-3)
                        assert (ra.kept, ra.broke_at, ra.f_t) == (rb.kept, rb.broke_at, rb.f_t), (options, t)
                        obs = np.clip(ra.forecast_observations[0] + rng.uniform(-0.3, 0.3, 3), -3, 3)
                    a.close()
                    b.close()
        finally:
            baseline.terminate()
            baseline.wait(10)
    finally:
        server.stop()


def start_baseline(bundles: pathlib.Path) -> tuple[subprocess.Popen[str], str]:
    """The Python baseline serving `bundles`, and its address."""
    baseline = subprocess.Popen(
        [sys.executable, str(REPO / "clients" / "python" / "baseline" / "server.py"), "--bundles", str(bundles), "--listen", "127.0.0.1:0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert baseline.stdout is not None
    line = baseline.stdout.readline()
    assert line.startswith("listening on "), line
    return baseline, line.removeprefix("listening on ").strip()


def answers_alike(bundles: pathlib.Path, server: Server, bundle_default: bool = False) -> np.ndarray:
    """Steps both servers alike and compares every answer; returns prac serve's forecast
    observations. With `bundle_default`, no session sets a guard: the bundle's default_guard
    guards them all."""
    baseline, address = start_baseline(bundles)
    try:
        rng = np.random.default_rng(5)
        breaks = guarded_breaks = 0
        forecasts: list[np.ndarray] = []
        with Client(server.address, timeout=10) as ours, Client(address, timeout=10) as theirs:
            # The last two sessions guard their plans (prac.v1.PlanGuard).
            for epsilon, growth, every_critic, support_limit in (
                (1e-4, "grow 2", False, None),
                (1e-3, "fixed 6", False, None),
                (0.0, "grow 1", False, None),
                (1e-4, "fixed 6", True, None),
                (1e-4, "grow 2", True, 0.5),
            ):
                guard = {"every_critic": every_critic, "support_limit": support_limit}
                if bundle_default:
                    guard, every_critic = {}, True
                a = ours.session("pendulum", epsilon=epsilon, growth=growth, max_horizon=12, **guard)
                b = theirs.session("pendulum", epsilon=epsilon, growth=growth, max_horizon=12, **guard)
                obs = rng.uniform(-1, 1, 3)
                for t in range(120):
                    ra, rb = a.step(obs, new_episode=t % 40 == 0), b.step(obs, new_episode=t % 40 == 0)
                    np.testing.assert_allclose(ra.action, rb.action, atol=1e-3, err_msg=f"{growth} step {t}")
                    np.testing.assert_allclose(ra.forecast_actions, rb.forecast_actions, atol=1e-3)
                    np.testing.assert_allclose(ra.forecast_observations, rb.forecast_observations, atol=1e-3)
                    forecasts.extend(np.asarray(ra.forecast_observations).reshape(-1, 3))
                    assert (ra.kept, ra.broke_at, ra.f_t, ra.step, ra.episode) == (rb.kept, rb.broke_at, rb.f_t, rb.step, rb.episode), t
                    breaks += ra.broke_at is not None
                    guarded_breaks += ra.broke_at is not None and every_critic
                    # Near the plan's predictions, with noise: some plans hold, some break.
                    obs = np.clip(ra.forecast_observations[0] + rng.uniform(-0.3, 0.3, 3), -3, 3)
                assert a.close() == b.close() == 120
        assert breaks > 0
        assert guarded_breaks > 0, "no guarded plan broke"
        return np.array(forecasts)
    finally:
        baseline.terminate()
        baseline.wait(10)
