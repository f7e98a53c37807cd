"""The synchronous client: the calls, blocking; their logic is in `_core`."""

from __future__ import annotations

import queue
import threading
import time
from typing import Iterator

import grpc

from prac_client import _core, errors
from prac_client._channel import Balance, Tls, channel_options
from prac_client._core import ArrayLike, Request, Response, T
from prac_client._options import Growth
from prac_client.onboard import Fallback, PathLike
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client._proto.prac.v1 import prac_pb2_grpc as pb_grpc
from prac_client.types import Plan, PolicyInfo, StepResult

__all__ = ["Client", "Session"]


class Client(_core.ClientBase):
    """A connection to a prac server.

    >>> with Client("127.0.0.1:50051") as client:
    ...     with client.session("pendulum", epsilon_coef=0.005) as session:
    ...         result = session.step(obs)

    `token` and `tls` secure every call; `timeout` (seconds) bounds each. `affinity` sends
    `x-prac-affinity` with every call, so a proxy keeps this client on one replica. Sessions
    survive losing their server: on a session the server no longer knows, or while no server
    answers, a step re-opens the session with the plan it holds and is sent again, for up to
    `patience` seconds.

    Without a proxy, `balance="ring_hash"` (with `affinity`) hashes the affinity key over every
    address the target resolves to (`dns:///prac-headless:50051`, or
    `ipv4:10.0.0.1:50051,10.0.0.2:50051`), so the client's calls stay on one replica, and when
    that one is lost only its clients move. `authority` sets the name the server's certificate is
    checked against (and HTTP/2's :authority), which a target listing addresses needs.
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
        balance: Balance | None = None,
        authority: str | None = None,
    ) -> None:
        super().__init__(target, token=token, tls=tls, timeout=timeout, affinity=affinity, patience=patience)
        options = channel_options(balance, authority, affinity)
        if self._credentials is None:
            self._channel = grpc.insecure_channel(target, options=options)
        else:
            self._channel = grpc.secure_channel(target, self._credentials, options=options)
        self._stub = pb_grpc.PracStub(self._channel)

    def _call(
        self, rpc: grpc.UnaryUnaryMultiCallable[Request, Response], request: Request, timeout: float | None = None
    ) -> Response:
        try:
            return rpc(request, timeout=timeout or self.timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            raise _core.rpc_error(e, request) from None

    def policies(self) -> list[PolicyInfo]:
        return _core.policy_infos(self._call(self._stub.ListPolicies, pb.ListPoliciesRequest()))

    def policy(self, name: str) -> PolicyInfo:
        return _core.find_policy(self.policies(), name)

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
        every_critic: bool = False,
        support_limit: float | None = None,
        max_epsilon_coef: float | None = None,
        fallback: Fallback | PathLike | None = None,
    ) -> Session:
        """Opens a session (close it, or use it as a context manager). A seed means sampled
        actions unless sampled=False.

        `fallback` (a `prac export-onnx` folder, or a `prac_client.onboard.Fallback`) goes on
        on board when no server answers past the patience: the session's steps are replanned
        locally from the plan it holds (`StepResult.local`) until a server takes it back. It
        must be the server's bundle (checked now: FallbackFailed)."""
        request = _core.open_request(
            policy,
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
        opened = self._call(self._stub.OpenSession, request)
        try:
            checked = _core.fallback_for(fallback, opened)
        except errors.PracError:
            self._call(self._stub.CloseSession, pb.CloseSessionRequest(session_id=opened.session_id))
            raise
        return Session(self, opened, policy, checked)

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _StepStream:
    """One StepStream call: requests go through a queue, responses come back in order."""

    def __init__(self, client: Client) -> None:
        self._requests: queue.SimpleQueue[pb.StepRequest | None] = queue.SimpleQueue()
        self._call = client._stub.StepStream(self._sent(), metadata=client._metadata)
        self._responses = iter(self._call)

    def _sent(self) -> Iterator[pb.StepRequest]:
        while (request := self._requests.get()) is not None:
            yield request

    def step(self, request: pb.StepRequest, timeout: float | None) -> pb.StepResponse:
        self._requests.put(request)
        timer = threading.Timer(timeout, self._call.cancel) if timeout is not None else None
        if timer is not None:
            timer.start()
        try:
            return next(self._responses)
        except StopIteration:
            raise errors.ServerUnavailable("the server ended the step stream") from None
        except grpc.RpcError as e:
            if timer is not None and not timer.is_alive() and e.code() == grpc.StatusCode.CANCELLED:
                raise errors.DeadlineExceeded(f"no answer within {timeout} s") from None
            raise _core.rpc_error(e, request) from None
        finally:
            if timer is not None:
                timer.cancel()

    def close(self) -> None:
        self._requests.put(None)


class Session(_core.SessionBase):
    """A session on one policy, holding the server-side plan. Steps go over one bidirectional
    stream, opened on the first step and again after an error."""

    def __init__(self, client: Client, opened: pb.OpenSessionResponse, policy: str, fallback: Fallback | None = None) -> None:
        super().__init__(opened, policy, fallback)
        self._client = client
        self._stream: _StepStream | None = None

    def _run(self, flow: _core.Flow[T]) -> T:
        """Makes the calls `flow` asks for, in turn, until it returns."""
        reply: _core.Reply = None
        failed: errors.PracError | None = None
        while True:
            try:
                io = flow.send(reply) if failed is None else flow.throw(failed)
            except StopIteration as done:
                result: T = done.value
                return result
            try:
                reply, failed = self._do(io), None
            except errors.PracError as e:
                reply, failed = None, e

    def _do(self, io: _core.Io) -> _core.Reply:
        match io:
            case _core.SendStep(request):
                return self._send(request)
            case _core.GetPlan(request):
                return self._client._call(self._client._stub.GetPlan, request)
            case _core.OpenSession(request, timeout):
                return self._client._call(self._client._stub.OpenSession, request, timeout)
            case _core.Reach(timeout):
                stub = self._client._stub
                pending: _core.Pending = stub.ListPolicies.future(
                    pb.ListPoliciesRequest(), timeout=timeout, metadata=self._client._metadata
                )
                return pending
            case _core.Pause(seconds):
                time.sleep(seconds)
                return None

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

    def step(self, observation: ArrayLike, *, new_episode: bool = False) -> StepResult:
        """Sends the observed state; returns the action to execute now and the forecast. If the
        server lost the session or none answers, resumes it (see `Client`) and goes on."""
        return self._run(self._stepping(observation, new_episode, self._client.patience))

    def reset(self, observation: ArrayLike | None = None) -> StepResult | None:
        """Starts a new episode (Algorithm 1, line 4): the old plan is dropped and t restarts at
        0. With an observation, steps from it now; without, the next step starts the episode."""
        return self._run(self._resetting(observation, self._client.patience))

    def plan(self) -> Plan:
        """The committed plan now (empty before the first step)."""
        return self._as_plan(self._client._call(self._client._stub.GetPlan, self._plan_request()))

    def watch(self) -> Iterator[Plan]:
        """The plan now, then every change of it, until the session ends (closing the
        iterator cancels the call)."""
        request = self._watch_request()
        call = self._client._stub.WatchPlan(request, metadata=self._client._metadata)
        try:
            for p in call:
                yield self._as_plan(p)
        except grpc.RpcError as e:
            raise _core.rpc_error(e, request) from None
        finally:
            call.cancel()  # type: ignore[no-untyped-call]  # grpc-stubs leaves RpcContext.cancel untyped

    def close(self) -> int:
        """Closes the session; returns the steps it served."""
        if self._stream is not None:
            self._stream.close()
            self._stream = None
        request = self._close_request()
        if request is None:
            return 0
        return int(self._client._call(self._client._stub.CloseSession, request).steps)

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.close()
        except errors.PracError:
            # Expired or server gone: nothing left to close.
            pass
