"""The synchronous client."""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Iterator

import grpc
import numpy as np
import numpy.typing as npt

from prac_client import _resume, errors
from prac_client._channel import CHANNEL_OPTIONS, Tls, credentials, metadata
from prac_client._options import Growth, session_options
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client._proto.prac.v1 import prac_pb2_grpc as pb_grpc
from prac_client.types import Plan, PolicyInfo, SessionOptions, StepResult

ArrayLike = npt.ArrayLike


def observation_list(observation: ArrayLike) -> list[float]:
    """A flat list of float32 values (the wire type)."""
    return [float(v) for v in np.asarray(observation, dtype=np.float32).ravel()]


class Client:
    """A connection to a prac server.

    >>> with Client("127.0.0.1:50051") as client:
    ...     with client.session("pendulum", epsilon_coef=0.005) as session:
    ...         result = session.step(obs)

    `token` and `tls` secure every call; `timeout` (seconds) bounds each. `affinity` sends
    `x-prac-affinity` with every call, so a proxy keeps this client on one replica. Sessions
    survive losing their server: on a session the server no longer knows, or while no server
    answers, a step re-opens the session with the plan it holds and is sent again, for up to
    `patience` seconds.
    """

    def __init__(
        self,
        target: str,
        *,
        token: str | None = None,
        tls: Tls = None,
        timeout: float | None = None,
        affinity: str | None = None,
        patience: float = 10.0,
    ) -> None:
        creds = credentials(tls)
        if creds is None:
            self._channel = grpc.insecure_channel(target, options=CHANNEL_OPTIONS)
        else:
            self._channel = grpc.secure_channel(target, creds, options=CHANNEL_OPTIONS)
        self._stub: Any = pb_grpc.PracStub(self._channel)  # type: ignore[no-untyped-call]
        self._metadata = metadata(token, affinity)
        self.timeout = timeout
        self.target = target
        self.patience = patience

    def _call(self, rpc: str, request: Any) -> Any:
        try:
            return getattr(self._stub, rpc)(request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            raise errors.from_rpc_error(e, rpc) from None

    def policies(self) -> list[PolicyInfo]:
        response = self._call("ListPolicies", pb.ListPoliciesRequest())
        return [PolicyInfo.from_proto(p) for p in response.policies]

    def policy(self, name: str) -> PolicyInfo:
        for p in self.policies():
            if p.name == name:
                return p
        raise errors.PolicyNotFound(f"unknown policy '{name}'")

    def session(
        self,
        policy: str,
        *,
        epsilon: float | None = None,
        epsilon_coef: float | None = None,
        growth: Growth | None = None,
        max_horizon: int | None = None,
        seed: int | None = None,
        sampled: bool | None = None,
    ) -> Session:
        """Opens a session (close it, or use it as a context manager). A seed means sampled
        actions unless sampled=False."""
        options = session_options(
            epsilon=epsilon,
            epsilon_coef=epsilon_coef,
            growth=growth,
            max_horizon=max_horizon,
            seed=seed,
            sampled=sampled,
        )
        opened = self._call("OpenSession", pb.OpenSessionRequest(policy=policy, options=options))
        return Session(self, opened, policy)

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


_END = object()


class _StepStream:
    """One StepStream call: requests go through a queue, responses come back in order."""

    def __init__(self, client: Client) -> None:
        self.requests: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self.responses: Any = client._stub.StepStream(iter(self.requests.get, _END), metadata=client._metadata)

    def step(self, request: pb.StepRequest, timeout: float | None) -> pb.StepResponse:
        self.requests.put(request)
        timer = threading.Timer(timeout, self.responses.cancel) if timeout is not None else None
        if timer is not None:
            timer.start()
        try:
            response: pb.StepResponse = next(self.responses)
        except StopIteration:
            raise errors.ServerUnavailable("the server ended the step stream") from None
        except grpc.RpcError as e:
            if timer is not None and not timer.is_alive() and e.code() == grpc.StatusCode.CANCELLED:
                raise errors.DeadlineExceeded(f"no answer within {timeout} s") from None
            raise errors.from_rpc_error(e, "Step") from None
        finally:
            if timer is not None:
                timer.cancel()
        return response

    def close(self) -> None:
        self.requests.put(_END)


class Session:
    """A session on one policy, holding the server-side plan. Steps go over one bidirectional
    stream, opened on the first step and again after an error."""

    def __init__(self, client: Client, opened: pb.OpenSessionResponse, policy: str) -> None:
        self._client = client
        self.id: str = opened.session_id
        self.policy = PolicyInfo.from_proto(opened.policy)
        self.options = SessionOptions.from_proto(opened.options)
        self._stream: _StepStream | None = None
        self._new_episode = False
        self.closed = False
        self._policy_name = policy
        self._options_in_force = _resume.options_in_force(opened.options)
        # The plan the last answer committed: what a new server resumes from.
        self._held: pb.Plan | None = None
        self.resumes = 0
        """Times the session was re-opened with its plan on a server that did not know it."""

    def step(self, observation: ArrayLike, *, new_episode: bool = False) -> StepResult:
        """Sends the observed state; returns the action to execute now and the forecast. If the
        server lost the session or none answers, resumes it (see `Client`) and goes on."""
        if self.closed:
            raise errors.SessionNotFound(
                f"session '{self.id}' was closed by this client; open a new one with client.session(...)"
            )
        observed = observation_list(observation)
        new_episode = new_episode or self._new_episode
        give_up = time.monotonic() + self._client.patience
        while True:
            request = pb.StepRequest(session_id=self.id, observation=observed, new_episode=new_episode)
            try:
                response = self._send(request)
            except _resume.RESUMABLE:
                if time.monotonic() > give_up:
                    raise
                recovered = self._recover()
                if recovered is None:
                    continue
                response = recovered
            self._held = _resume.held_plan(response)
            self._new_episode = False
            return StepResult.from_proto(response, self.policy.act_dim, self.policy.obs_dim)

    def _send(self, request: pb.StepRequest) -> pb.StepResponse:
        if self._stream is None:
            self._stream = _StepStream(self._client)
        try:
            return self._stream.step(request, self._client.timeout)
        except errors.PracError:
            # gRPC ends a stream at its first error; the session itself is intact.
            self._stream.close()
            self._stream = None
            raise

    def _recover(self) -> pb.StepResponse | None:
        """After a failed step: the step's answer if the server applied it after all (its plan
        moved on), else None once a session exists to send it again to."""
        try:
            now = self._client._call("GetPlan", pb.GetPlanRequest(session_id=self.id))
        except (errors.SessionNotFound, errors.SessionExpired):
            self._reopen()
            return None
        except errors.ServerUnavailable:
            time.sleep(_resume.RETRY_PAUSE)
            return None
        if _resume.applied(self._held, now):
            return _resume.answer_from_plan(self._held, now)
        return None

    def _reopen(self) -> None:
        request = pb.OpenSessionRequest(policy=self._policy_name, options=self._options_in_force)
        if self._held is not None:
            request.resume.CopyFrom(self._held)
        try:
            opened = self._client._call("OpenSession", request)
        except errors.ServerUnavailable:
            time.sleep(_resume.RETRY_PAUSE)
            return
        self.id = opened.session_id
        self.resumes += 1

    def reset(self, observation: ArrayLike | None = None) -> StepResult | None:
        """Starts a new episode (Algorithm 1, line 4): the old plan is dropped and t restarts at
        0. With an observation, steps from it now; without, the next step starts the episode."""
        if observation is None:
            self._new_episode = True
            return None
        return self.step(observation, new_episode=True)

    def plan(self) -> Plan:
        """The committed plan now (empty before the first step)."""
        p = self._client._call("GetPlan", pb.GetPlanRequest(session_id=self.id))
        return Plan.from_proto(p, self.policy.act_dim, self.policy.obs_dim)

    def watch(self) -> Iterator[Plan]:
        """The plan now, then every change of it, until the session ends (closing the
        iterator cancels the call)."""
        call = self._client._stub.WatchPlan(
            pb.WatchPlanRequest(session_id=self.id), metadata=self._client._metadata
        )
        try:
            for p in call:
                yield Plan.from_proto(p, self.policy.act_dim, self.policy.obs_dim)
        except grpc.RpcError as e:
            raise errors.from_rpc_error(e, "WatchPlan") from None
        finally:
            call.cancel()

    def close(self) -> int:
        """Closes the session; returns the steps it served."""
        if self._stream is not None:
            self._stream.close()
            self._stream = None
        if self.closed:
            return 0
        self.closed = True
        response = self._client._call("CloseSession", pb.CloseSessionRequest(session_id=self.id))
        return int(response.steps)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.close()
        except errors.PracError:
            # Expired or server gone: nothing left to close.
            pass
