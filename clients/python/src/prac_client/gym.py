"""Play a gymnasium environment with a served policy."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from prac_client._client import Session


@dataclass(frozen=True)
class EpisodeResult:
    episode_return: float
    """Undiscounted sum of rewards."""
    discounted_return: float
    """Sum of gamma^t r_t with the policy's gamma (or the one given)."""
    steps: int
    forecasts: npt.NDArray[np.int64]
    """f_t of every step (t + 1 - i: how long ago the executed action was committed)."""
    replans: int
    """Steps at which the previous plan broke."""
    terminated: bool
    truncated: bool
    local_steps: int = 0
    """Steps replanned on board by the session's fallback (no server answered)."""

    @property
    def mean_forecast(self) -> float:
        """The paper's episode forecast: the mean of f_t."""
        return float(self.forecasts.mean()) if self.steps else 0.0


def run_episode(
    env: Any,
    session: Session,
    *,
    seed: int | None = None,
    gamma: float | None = None,
    max_steps: int | None = None,
) -> EpisodeResult:
    """Resets `env` (with `seed`), starts a new episode on the session, and steps until the
    episode ends (or `max_steps`), executing the server's action each step (or, for a session
    opened with `fallback=` while no server answers, the one replanned on board)."""
    gamma = session.policy.gamma if gamma is None else gamma
    observation, _ = env.reset(seed=seed)
    result = session.reset(observation)
    assert result is not None
    dtype = getattr(env.action_space, "dtype", np.float32)
    total, discounted, discount = 0.0, 0.0, 1.0
    forecasts: list[int] = []
    replans = 0
    terminated = truncated = False
    steps = local = 0
    while True:
        forecasts.append(result.f_t)
        local += result.local
        if result.broke_at is not None:
            replans += 1
        observation, reward, terminated, truncated, _ = env.step(np.asarray(result.action, dtype=dtype))
        steps += 1
        total += float(reward)
        discounted += discount * float(reward)
        discount *= gamma
        if terminated or truncated or (max_steps is not None and steps >= max_steps):
            break
        result = session.step(observation)
    return EpisodeResult(
        episode_return=total,
        discounted_return=discounted,
        steps=steps,
        forecasts=np.asarray(forecasts, dtype=np.int64),
        replans=replans,
        terminated=bool(terminated),
        truncated=bool(truncated),
        local_steps=local,
    )
