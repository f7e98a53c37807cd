"""The logic of the sync and asyncio clients, without I/O: the requests they send, what they make
of the answers, how a failed call reads, and how a session resumes. Each client makes the calls.

A session's step is a generator (`SessionBase._stepping`) that yields the I/O it needs (`Io`) and
is sent each reply, or thrown the call's `PracError`; `prac_client.Session` drives it with
blocking calls, `prac_client.aio.Session` with awaits.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Generator, Protocol, TypeVar

import grpc
import numpy as np
import numpy.typing as npt
from google.protobuf.message import Message

from prac_client import _resume, errors
from prac_client.onboard import Fallback, OnBoard, PathLike
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


def fallback_for(fallback: Fallback | PathLike | None, opened: pb.OpenSessionResponse) -> Fallback | None:
    """The session's fallback, checked against the session the server opened: the same bundle
    (content hash) and a deterministic session. Raises FallbackFailed."""
    if fallback is None:
        return None
    if not isinstance(fallback, Fallback):
        fallback = Fallback(fallback)
    if fallback.content_hash != opened.policy.content_hash:
        raise errors.FallbackFailed(
            f"the fallback ({fallback.content_hash}) is not the server's '{opened.policy.name}' "
            f"({opened.policy.content_hash}); export the bundle the server serves"
        )
    if opened.options.sampled:
        raise errors.FallbackFailed("the on-board fallback replans deterministic sessions only; open without sampled")
    return fallback


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
    """Call OpenSession (within `timeout` seconds, else the client's); the reply is the
    pb.OpenSessionResponse."""

    request: pb.OpenSessionRequest
    timeout: float | None = None


@dataclass(frozen=True)
class Reach:
    """Start a ListPolicies within `timeout` seconds without waiting for it: the reply is a
    `Pending` that says whether a server answered. The local session asks this way, so that
    looking for a server never holds up a control loop's step."""

    timeout: float


class Pending(Protocol):
    """A call started by `Reach` (a grpc.Future, an asyncio.Task)."""

    def done(self) -> bool: ...

    def exception(self) -> BaseException | None: ...


@dataclass(frozen=True)
class Pause:
    """Wait before trying again; the reply is None."""

    seconds: float


Io = SendStep | GetPlan | OpenSession | Reach | Pause
Reply = pb.StepResponse | pb.Plan | pb.OpenSessionResponse | Pending | None
Flow = Generator[Io, Reply, T]
"""Logic that yields the I/O it needs and returns a T."""


def _answered(pending: Pending) -> bool:
    try:
        return pending.exception() is None
    except BaseException:  # cancelled
        return False


def _reply(reply: Reply, kind: type[Response]) -> Response:
    if not isinstance(reply, kind):
        raise TypeError(f"expected a {kind.__name__} reply, got {type(reply).__name__}")
    return reply


class _Unknown:
    """Whether a failed step was applied is not known yet."""


UNKNOWN = _Unknown()


class SessionBase:
    """A session's state and logic; the sync and asyncio sessions make its calls."""

    def __init__(self, opened: pb.OpenSessionResponse, policy: str, fallback: Fallback | None = None) -> None:
        self.id: str = opened.session_id
        self.policy = PolicyInfo.from_proto(opened.policy)
        self.options = SessionOptions.from_proto(opened.options)
        self.closed = False
        self._new_episode = False
        self._policy_name = policy
        self._resolved = opened.options
        self._options_in_force = _resume.options_in_force(opened.options)
        # The plan the last answer committed: what a new server resumes from.
        self._held: pb.Plan | None = None
        self.resumes = 0
        """Times the session was re-opened with its plan on a server that did not know it."""
        self._fallback = fallback
        # The session going on on board, while no server has it.
        self._on_board: OnBoard | None = None
        self.local_steps = 0
        """Steps answered on board by the fallback."""
        self._unreported_local_steps = 0
        self.probe_every = _resume.PROBE_EVERY
        """While local, seconds between tries to resume on a server."""
        self.probe_timeout = _resume.PROBE_TIMEOUT
        """How long such a try waits for a server."""
        self._next_probe = 0.0
        self._reaching: Pending | None = None
        # With a fallback, a call that times out (a link that stopped forwarding) is a lost
        # server too: the session goes local rather than failing the step.
        self._lost: tuple[type[errors.PracError], ...] = _resume.RESUMABLE + (
            (errors.DeadlineExceeded,) if fallback is not None else ()
        )

    @property
    def local(self) -> bool:
        """Whether the session is going on on board now (no server answered past the patience)."""
        return self._on_board is not None

    def _stepping(self, observation: ArrayLike, new_episode: bool, patience: float) -> Flow[StepResult]:
        """One step, resumed (up to `patience` seconds) where the server lost the session or none
        answers: on a server without the session, it is re-opened with the plan it holds and the
        step sent again; a step the server applied although its answer was lost is not sent again.
        With a fallback, past the patience the step is replanned on board, and so are the next
        until a server takes the session back (tried every `probe_every` seconds)."""
        if self.closed:
            raise errors.SessionNotFound(
                f"session '{self.id}' was closed by this client; open a new one with client.session(...)"
            )
        observed = observation_list(observation)
        new_episode = new_episode or self._new_episode
        if self.local:
            yield from self._looking_for_a_server()
        if self.local:
            return self._step_on_board(observed, new_episode)
        give_up = time.monotonic() + patience
        while True:
            request = pb.StepRequest(session_id=self.id, observation=observed, new_episode=new_episode)
            try:
                response = _reply((yield SendStep(request)), pb.StepResponse)
            except self._lost as failure:
                # Until a server says whether it applied the step, it is not sent again.
                recovered: pb.StepResponse | None | _Unknown = UNKNOWN
                while isinstance(recovered, _Unknown):
                    if time.monotonic() > give_up:
                        if self._fallback is None:
                            raise failure
                        self._on_board = self._fallback.start(self._resolved, self._held)
                        self._next_probe = time.monotonic() + self.probe_every
                        return self._step_on_board(observed, new_episode)
                    recovered = yield from self._recovering()
                if recovered is None:
                    continue
                response = recovered
            self._held = _resume.held_plan(response)
            self._new_episode = False
            return StepResult.from_proto(response, self.policy.act_dim, self.policy.obs_dim)

    def _step_on_board(self, observed: list[float], new_episode: bool) -> StepResult:
        """One step replanned by the fallback. If the fallback fails, the error carries the held
        plan's action for this step (and the session holds the rest of that plan)."""
        assert self._on_board is not None
        try:
            response = self._on_board.step(observed, new_episode)
        except errors.FallbackFailed as e:
            following = _resume.following(self._held)
            if following is not None and not new_episode:
                self._held = _resume.held_plan(following)
                e.held = StepResult.from_proto(following, self.policy.act_dim, self.policy.obs_dim, local=True)
                self.local_steps += 1
                self._unreported_local_steps += 1
            raise
        self._held = _resume.held_plan(response)
        self._new_episode = False
        self.local_steps += 1
        self._unreported_local_steps += 1
        return StepResult.from_proto(response, self.policy.act_dim, self.policy.obs_dim, local=True)

    def _looking_for_a_server(self) -> Flow[None]:
        """While local: every `probe_every` seconds a call that waits for nobody asks whether a
        server answers; once one did, the session is re-opened there with the local plan."""
        reaching = self._reaching
        if reaching is not None and reaching.done():
            self._reaching = None
            if _answered(reaching):
                yield from self._probing()
        if self._reaching is None and self.local and time.monotonic() >= self._next_probe:
            self._next_probe = time.monotonic() + self.probe_every
            pending = yield Reach(self.probe_timeout)
            if pending is None or isinstance(pending, Message):
                raise TypeError(f"expected a pending call, got {type(pending).__name__}")
            self._reaching = pending

    def _probing(self) -> Flow[None]:
        """Re-opens the session on a server with the local plan, if one answers within
        `probe_timeout`; the next steps are served there."""
        assert self._fallback is not None
        request = pb.OpenSessionRequest(
            policy=self._policy_name, options=self._options_in_force, local_steps=self._unreported_local_steps
        )
        if self._held is not None:
            request.resume.CopyFrom(self._held)
        try:
            opened = _reply((yield OpenSession(request, self.probe_timeout)), pb.OpenSessionResponse)
        except errors.PracError:
            return
        self.id = opened.session_id
        self.resumes += 1
        self._unreported_local_steps = 0
        self._on_board = None

    def _recovering(self) -> Flow[pb.StepResponse | None | _Unknown]:
        """After a failed step: the step's answer if the server applied it after all (its plan
        moved on), None once a session exists to send it again to, or UNKNOWN while no server
        answers (the step may have been applied: it must not be sent again yet)."""
        try:
            now = _reply((yield GetPlan(self._plan_request())), pb.Plan)
        except (errors.SessionNotFound, errors.SessionExpired):
            yield from self._reopening()
            return None
        except self._lost:
            yield Pause(_resume.RETRY_PAUSE)
            return UNKNOWN
        if _resume.applied(self._held, now):
            return _resume.answer_from_plan(self._held, now)
        return None

    def _reopening(self) -> Flow[None]:
        request = pb.OpenSessionRequest(policy=self._policy_name, options=self._options_in_force)
        if self._held is not None:
            request.resume.CopyFrom(self._held)
        try:
            opened = _reply((yield OpenSession(request)), pb.OpenSessionResponse)
        except self._lost:
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
