"""prac_client.gym with gymnasium's Pendulum-v1 and the served (random) Pendulum-shaped policy."""

from __future__ import annotations

import gymnasium
import numpy as np

from prac_client import Client
from prac_client.gym import run_episode


def test_run_episode_reports_returns_and_forecasts(client: Client) -> None:
    env = gymnasium.make("Pendulum-v1")
    with client.session("pendulum", epsilon_coef=0.01, max_horizon=16) as session:
        result = run_episode(env, session, seed=3)
        assert result.steps == 200 and result.truncated and not result.terminated
        assert result.forecasts.shape == (200,)
        assert result.forecasts[0] == 1
        assert 1.0 <= result.mean_forecast <= 16.0
        # Pendulum rewards are in [-16.3, 0]: check the sums against the rewards replayed.
        assert -16.3 * 200 <= result.episode_return <= 0.0
        assert result.episode_return <= result.discounted_return <= 0.0
        # The same seed replays the same episode (deterministic policy, fresh plan).
        again = run_episode(env, session, seed=3)
        assert again.episode_return == result.episode_return
        np.testing.assert_array_equal(again.forecasts, result.forecasts)
