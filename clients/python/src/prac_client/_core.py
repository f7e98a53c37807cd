"""The logic of the sync and asyncio clients, without I/O: the requests they send, what they make
of the answers, how a failed call reads, and how a session resumes. Each client makes the calls.

A session's step is a generator (`SessionBase._stepping`) that yields the I/O it needs (`Io`) and
is sent each reply, or thrown the call's `PracError`; `prac_client.Session` drives it with
blocking calls, `prac_client.aio.Session` with awaits.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Generator, TypeVar

import grpc
import numpy as np
import numpy.typing as npt
from google.protobuf.message import Message

from prac_client import _resume, errors
from prac_client._channel import Tls, credentials, metadata
from prac_client._options import Growth, session_options
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client.types import Plan, PolicyInfo, SessionOptions, StepResult

ArrayLike = npt.ArrayLike
T = TypeVar("T")
Request = TypeVar("Request", bound=Message)
Response = TypeVar("Response", bound=Message)


def observation_list(observation: ArrayLike) -> list[float]:
    """A flat list of float32 values (the wire type)."""
    return [float(v) for v in np.asarray(observation, dtype=np.float32).ravel()]


def rpc_error(error: grpc.RpcError, request: Message) -> errors.PracError:
    """A failed call as the client's exception; the RPC is named by its request (StepRequest: Step)."""
    return errors.from_rpc_error(error, request.DESCRIPTOR.name.removesuffix("Request"))


def policy_infos(response: pb.ListPoliciesResponse) -> list[PolicyInfo]:
    return [PolicyInfo.from_proto(p) for p in response.policies]


def find_policy(policies: list[PolicyInfo], name: str) -> PolicyInfo:
    for p in policies:
        if p.name == name:
            return p
    raise errors.PolicyNotFound(f"unknown policy '{name}'")


def open_request(
    policy: str,
    *,
    epsilon: float | None,
    epsilon_coef: float | None,
    growth: Growth | None,
    max_horizon: int | None,
    seed: int | None,
    sampled: bool | None,
    every_critic: bool = False,
    support_limit: float | None = None,
    max_epsilon_coef: float | None = None,
) -> pb.OpenSessionRequest:
    """OpenSession's request; invalid options are a ValueError before any call."""
    options = session_options(
        epsilon=epsilon,
        epsilon_coef=epsilon_coef,
        growth=growth,
        max_horizon=max_horizon,
        seed=seed,
        sampled=sampled,
        every_critic=every_critic,
        support_limit=support_limit,
        max_epsilon_coef=max_epsilon_coef,
    )
    return pb.OpenSessionRequest(policy=policy, options=options)


class ClientBase:
    """A client's settings; the sync and asyncio clients add the channel and the calls."""

    def __init__(
        self,
        target: str,
        *,
        token: str | None,
        tls: Tls,
        timeout: float | None,
        affinity: str | None,
        patience: float,
    ) -> None:
        self._credentials = credentials(tls)
        self._metadata = metadata(token, affinity)
        self.timeout = timeout
        self.target = target
        self.patience = patience


@dataclass(frozen=True)
class SendStep:
    """Send a step on the session's stream; the reply is its pb.StepResponse."""

    request: pb.StepRequest


@dataclass(frozen=True)
class GetPlan:
    """Call GetPlan; the reply is the pb.Plan."""

    request: pb.GetPlanRequest


@dataclass(frozen=True)
class OpenSession:
    """Call OpenSession; the reply is the pb.OpenSessionResponse."""

    request: pb.OpenSessionRequest


@dataclass(frozen=True)
class Pause:
    """Wait before trying again; the reply is None."""

    seconds: float


Io = SendStep | GetPlan | OpenSession | Pause
Reply = pb.StepResponse | pb.Plan | pb.OpenSessionResponse | None
Flow = Generator[Io, Reply, T]
"""Logic that yields the I/O it needs and returns a T."""


def _reply(reply: Reply, kind: type[Response]) -> Response:
    if not isinstance(reply, kind):
        raise TypeError(f"expected a {kind.__name__} reply, got {type(reply).__name__}")
    return reply


class SessionBase:
    """A session's state and logic; the sync and asyncio sessions make its calls."""

    def __init__(self, opened: pb.OpenSessionResponse, policy: str) -> None:
        self.id: str = opened.session_id
        self.policy = PolicyInfo.from_proto(opened.policy)
        self.options = SessionOptions.from_proto(opened.options)
        self.closed = False
        self._new_episode = False
        self._policy_name = policy
        self._options_in_force = _resume.options_in_force(opened.options)
        # The plan the last answer committed: what a new server resumes from.
        self._held: pb.Plan | None = None
        self.resumes = 0
        """Times the session was re-opened with its plan on a server that did not know it."""

    def _stepping(self, observation: ArrayLike, new_episode: bool, patience: float) -> Flow[StepResult]:
        """One step, resumed (up to `patience` seconds) where the server lost the session or none
        answers: on a server without the session, it is re-opened with the plan it holds and the
        step sent again; a step the server applied although its answer was lost is not sent again."""
        if self.closed:
            raise errors.SessionNotFound(
                f"session '{self.id}' was closed by this client; open a new one with client.session(...)"
            )
        observed = observation_list(observation)
        new_episode = new_episode or self._new_episode
        give_up = time.monotonic() + patience
        while True:
            request = pb.StepRequest(session_id=self.id, observation=observed, new_episode=new_episode)
            try:
                response = _reply((yield SendStep(request)), pb.StepResponse)
            except _resume.RESUMABLE:
                if time.monotonic() > give_up:
                    raise
                recovered = yield from self._recovering()
                if recovered is None:
                    continue
                response = recovered
            self._held = _resume.held_plan(response)
            self._new_episode = False
            return StepResult.from_proto(response, self.policy.act_dim, self.policy.obs_dim)

    def _recovering(self) -> Flow[pb.StepResponse | None]:
        """After a failed step: the step's answer if the server applied it after all (its plan
        moved on), else None once a session exists to send it again to."""
        try:
            now = _reply((yield GetPlan(self._plan_request())), pb.Plan)
        except (errors.SessionNotFound, errors.SessionExpired):
            yield from self._reopening()
            return None
        except errors.ServerUnavailable:
            yield Pause(_resume.RETRY_PAUSE)
            return None
        if _resume.applied(self._held, now):
            return _resume.answer_from_plan(self._held, now)
        return None

    def _reopening(self) -> Flow[None]:
        request = pb.OpenSessionRequest(policy=self._policy_name, options=self._options_in_force)
        if self._held is not None:
            request.resume.CopyFrom(self._held)
        try:
            opened = _reply((yield OpenSession(request)), pb.OpenSessionResponse)
        except errors.ServerUnavailable:
            yield Pause(_resume.RETRY_PAUSE)
            return
        self.id = opened.session_id
        self.resumes += 1

    def _resetting(self, observation: ArrayLike | None, patience: float) -> Flow[StepResult | None]:
        """A new episode: stepped from `observation` now, or started by the next step."""
        if observation is None:
            self._new_episode = True
            return None
        return (yield from self._stepping(observation, True, patience))

    def _plan_request(self) -> pb.GetPlanRequest:
        return pb.GetPlanRequest(session_id=self.id)

    def _watch_request(self) -> pb.WatchPlanRequest:
        return pb.WatchPlanRequest(session_id=self.id)

    def _as_plan(self, plan: pb.Plan) -> Plan:
        return Plan.from_proto(plan, self.policy.act_dim, self.policy.obs_dim)

    def _close_request(self) -> pb.CloseSessionRequest | None:
        """CloseSession's request, or None if this client closed the session already."""
        if self.closed:
            return None
        self.closed = True
        return pb.CloseSessionRequest(session_id=self.id)
