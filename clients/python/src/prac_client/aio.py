"""The asyncio client (grpc.aio): the same API with coroutines.

>>> async with Client("127.0.0.1:50051") as client:
...     async with client.session("pendulum", epsilon_coef=0.005) as session:
...         result = await session.step(obs)
"""

from __future__ import annotations

import asyncio
from typing import Any, AsyncIterator, Generator

import grpc
import grpc.aio

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
    """The asyncio twin of `prac_client.Client`, with the same options (token, tls, timeout,
    affinity, patience, balance, authority) and sessions that resume the same way."""

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
            self._channel = grpc.aio.insecure_channel(target, options=options)
        else:
            self._channel = grpc.aio.secure_channel(target, self._credentials, options=options)
        self._stub = pb_grpc.PracStub(self._channel)

    async def _call(
        self, rpc: grpc.aio.UnaryUnaryMultiCallable[Request, Response], request: Request, timeout: float | None = None
    ) -> Response:
        try:
            return await rpc(request, timeout=timeout or self.timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            raise _core.rpc_error(e, request) from None

    async def policies(self) -> list[PolicyInfo]:
        return _core.policy_infos(await self._call(self._stub.ListPolicies, pb.ListPoliciesRequest()))

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
    ) -> _Opening:
        """`await client.session(...)` or `async with client.session(...) as session`; `fallback`
        as in `prac_client.Client.session`."""
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
        return _Opening(self, request, fallback)

    async def close(self) -> None:
        await self._channel.close(grace=None)

    async def __aenter__(self) -> Client:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _Opening:
    """An OpenSession in flight: awaitable, or an async context manager that closes the session."""

    def __init__(self, client: Client, request: pb.OpenSessionRequest, fallback: Fallback | PathLike | None) -> None:
        self._client = client
        self._request = request
        self._fallback = fallback
        self._session: Session | None = None

    async def _open(self) -> Session:
        opened = await self._client._call(self._client._stub.OpenSession, self._request)
        try:
            checked = _core.fallback_for(self._fallback, opened)
        except errors.PracError:
            await self._client._call(self._client._stub.CloseSession, pb.CloseSessionRequest(session_id=opened.session_id))
            raise
        return Session(self._client, opened, self._request.policy, checked)

    def __await__(self) -> Generator[Any, None, Session]:
        return self._open().__await__()

    async def __aenter__(self) -> Session:
        self._session = await self._open()
        return self._session

    async def __aexit__(self, *exc: object) -> None:
        if self._session is not None:
            try:
                await self._session.close()
            except errors.PracError:
                pass


class Session(_core.SessionBase):
    """The asyncio twin of `prac_client.Session`."""

    def __init__(self, client: Client, opened: pb.OpenSessionResponse, policy: str, fallback: Fallback | None = None) -> None:
        super().__init__(opened, policy, fallback)
        self._client = client
        self._stream: grpc.aio.StreamStreamCall[pb.StepRequest, pb.StepResponse] | None = None

    async def _run(self, flow: _core.Flow[T]) -> T:
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
                reply, failed = await self._do(io), None
            except errors.PracError as e:
                reply, failed = None, e

    async def _do(self, io: _core.Io) -> _core.Reply:
        match io:
            case _core.SendStep(request):
                return await self._send(request)
            case _core.GetPlan(request):
                return await self._client._call(self._client._stub.GetPlan, request)
            case _core.OpenSession(request, timeout):
                return await self._client._call(self._client._stub.OpenSession, request, timeout)
            case _core.Reach(timeout):
                call = self._client._stub.ListPolicies(
                    pb.ListPoliciesRequest(), timeout=timeout, metadata=self._client._metadata
                )
                return asyncio.ensure_future(call)
            case _core.Pause(seconds):
                await asyncio.sleep(seconds)
                return None

    async def _send(self, request: pb.StepRequest) -> pb.StepResponse:
        if self._stream is None:
            self._stream = self._client._stub.StepStream(None, metadata=self._client._metadata)
        stream = self._stream
        try:
            await stream.write(request)
            response = await asyncio.wait_for(stream.read(), self._client.timeout)
            if not isinstance(response, pb.StepResponse):  # grpc.aio.EOF: the stream ended
                raise _core.rpc_error(_Status(await stream.code(), await stream.details()), request)
        except grpc.RpcError as e:
            self._drop_stream()
            raise _core.rpc_error(e, request) from None
        except asyncio.TimeoutError:
            self._drop_stream()
            raise errors.DeadlineExceeded(f"no answer within {self._client.timeout} s") from None
        except errors.PracError:
            self._drop_stream()
            raise
        return response

    def _drop_stream(self) -> None:
        if self._stream is not None:
            self._stream.cancel()
            self._stream = None

    async def step(self, observation: ArrayLike, *, new_episode: bool = False) -> StepResult:
        """As `prac_client.Session.step`, resuming the same way."""
        return await self._run(self._stepping(observation, new_episode, self._client.patience))

    async def reset(self, observation: ArrayLike | None = None) -> StepResult | None:
        return await self._run(self._resetting(observation, self._client.patience))

    async def plan(self) -> Plan:
        return self._as_plan(await self._client._call(self._client._stub.GetPlan, self._plan_request()))

    async def watch(self) -> AsyncIterator[Plan]:
        request = self._watch_request()
        call = self._client._stub.WatchPlan(request, metadata=self._client._metadata)
        try:
            async for p in call:
                yield self._as_plan(p)
        except grpc.RpcError as e:
            raise _core.rpc_error(e, request) from None
        finally:
            call.cancel()

    async def close(self) -> int:
        if self._stream is not None:
            try:
                await self._stream.done_writing()
            except grpc.RpcError:
                pass
            self._drop_stream()
        request = self._close_request()
        if request is None:
            return 0
        return int((await self._client._call(self._client._stub.CloseSession, request)).steps)

    async def __aenter__(self) -> Session:
        return self

    async def __aexit__(self, *exc: object) -> None:
        try:
            await self.close()
        except errors.PracError:
            pass


class _Status(grpc.RpcError):
    """A stream's final status, shaped like an RpcError for errors.from_rpc_error."""

    def __init__(self, code: grpc.StatusCode, details: str | None) -> None:
        super().__init__(details)
        self._code = code
        self._details = details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str | None:
        return self._details
