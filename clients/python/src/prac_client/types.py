"""Plain Python views of the server's messages, with numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
import numpy.typing as npt

from prac_client._proto.prac.v1 import prac_pb2 as pb

FloatArray = npt.NDArray[np.float32]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class ValueScale:
    """Discounted start-state values of the policy (V_pi) and of uniform random actions."""

    v_pi: float
    v_rand: float


@dataclass(frozen=True)
class PlanGuard:
    """Conditions that also break a plan, beyond the paper's test (all off: the paper's test)."""

    every_critic: bool
    support_limit: float
    # Not a break: the session's eps is held to at most this coefficient (0: no limit).
    max_epsilon_coef: float = 0.0

    @staticmethod
    def from_proto(g: pb.PlanGuard) -> PlanGuard:
        return PlanGuard(g.every_critic, g.support_limit, g.max_epsilon_coef)


@dataclass(frozen=True)
class Feature:
    """One observation or action entry: its name and unit (or scaling)."""

    name: str
    unit: str


@dataclass(frozen=True)
class PolicyInfo:
    name: str
    domain: str
    obs_dim: int
    act_dim: int
    action_low: FloatArray
    action_high: FloatArray
    gamma: float
    value_scale: ValueScale | None
    content_hash: str
    q_aggregation: str
    format_version: int
    # The guard of a session that sets none (the bundle's default_guard).
    default_guard: PlanGuard
    # Seconds per step on the bundle's domain; None where the server does not know the domain.
    control_period: float | None = None
    # What each observation and action entry is, in order; empty where the server does not know
    # the domain.
    observation_features: tuple[Feature, ...] = ()
    action_features: tuple[Feature, ...] = ()

    @staticmethod
    def from_proto(p: pb.PolicyInfo) -> PolicyInfo:
        scale = ValueScale(p.value_scale.v_pi, p.value_scale.v_rand) if p.HasField("value_scale") else None
        return PolicyInfo(
            name=p.name,
            domain=p.domain,
            obs_dim=p.obs_dim,
            act_dim=p.act_dim,
            action_low=np.asarray(p.action_low, dtype=np.float32),
            action_high=np.asarray(p.action_high, dtype=np.float32),
            gamma=p.gamma,
            value_scale=scale,
            content_hash=p.content_hash,
            q_aggregation=p.q_aggregation,
            format_version=p.format_version,
            default_guard=PlanGuard.from_proto(p.default_guard),
            control_period=p.control_period if p.HasField("control_period") else None,
            observation_features=tuple(Feature(f.name, f.unit) for f in p.observation_features),
            action_features=tuple(Feature(f.name, f.unit) for f in p.action_features),
        )


@dataclass(frozen=True)
class SessionOptions:
    """The options in force for a session (defaults filled in, epsilon absolute)."""

    epsilon: float
    growth_mode: str
    growth: int
    max_horizon: int
    sampled: bool
    seed: int
    # The guard in force.
    guard: PlanGuard

    @staticmethod
    def from_proto(o: pb.ResolvedOptions) -> SessionOptions:
        guard = PlanGuard.from_proto(o.guard)
        return SessionOptions(o.epsilon, o.growth_mode, o.growth, o.max_horizon, o.sampled, o.seed, guard)


def _planned(entries: Sequence[Any], act_dim: int, obs_dim: int) -> tuple[FloatArray, FloatArray, IntArray]:
    # One flat list per field: several times faster than numpy over per-entry lists.
    n = len(entries)
    actions = np.array([x for e in entries for x in e.action], dtype=np.float32).reshape(n, act_dim)
    observations = np.array([x for e in entries for x in e.predicted_observation], dtype=np.float32)
    decided = np.array([e.decided_at for e in entries], dtype=np.int64)
    return actions, observations.reshape(n, obs_dim), decided


@dataclass(frozen=True)
class StepResult:
    """One step: the action to execute now and the committed forecast from this step on."""

    action: FloatArray
    """[act_dim]: execute this now (= forecast_actions[0])."""
    forecast_actions: FloatArray
    """[n, act_dim]: the committed actions for steps t, t+1, ..., t+n-1."""
    forecast_observations: FloatArray
    """[n, obs_dim]: the model's predicted observation after each of them."""
    decided_at: IntArray
    """[n]: the step at which Replan decided each action."""
    kept: int
    """Actions of the previous plan that passed the test and were kept."""
    broke_at: int | None
    """Index, in the previous remaining plan, of the action that failed the test."""
    f_t: int
    """t + 1 - i for the action executed now, decided at step i (1: decided now)."""
    step: int
    episode: int
    local: bool = False
    """Replanned on board by the session's fallback (no server answered), not served."""

    @property
    def forecast_length(self) -> int:
        """How many actions the server has committed to, the current one included."""
        return int(self.forecast_actions.shape[0])

    @staticmethod
    def from_proto(r: pb.StepResponse, act_dim: int, obs_dim: int, *, local: bool = False) -> StepResult:
        actions, observations, decided = _planned(r.forecast, act_dim, obs_dim)
        return StepResult(
            action=np.asarray(r.action, dtype=np.float32),
            forecast_actions=actions,
            forecast_observations=observations,
            decided_at=decided,
            kept=r.kept,
            broke_at=r.broke_at if r.HasField("broke_at") else None,
            f_t=r.f_t,
            step=r.step,
            episode=r.episode,
            local=local,
        )


@dataclass(frozen=True)
class Plan:
    """A session's committed plan: actions[j] is for step start_step + j."""

    session_id: str
    episode: int
    start_step: int
    actions: FloatArray
    observations: FloatArray
    decided_at: IntArray

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @staticmethod
    def from_proto(p: pb.Plan, act_dim: int, obs_dim: int) -> Plan:
        actions, observations, decided = _planned(p.actions, act_dim, obs_dim)
        return Plan(p.session_id, p.episode, p.start_step, actions, observations, decided)
