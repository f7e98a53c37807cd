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
from grpc.aio import EOF  # type: ignore[attr-defined]

from prac_client import _resume, errors
from prac_client._channel import CHANNEL_OPTIONS, Tls, credentials, metadata
from prac_client._client import ArrayLike, observation_list
from prac_client._options import Growth, session_options
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client._proto.prac.v1 import prac_pb2_grpc as pb_grpc
from prac_client.types import Plan, PolicyInfo, SessionOptions, StepResult

__all__ = ["Client", "Session"]


class Client:
    """The asyncio twin of `prac_client.Client`, with the same options (token, tls, timeout,
    affinity, patience) and sessions that resume the same way."""

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
            self._channel = grpc.aio.insecure_channel(target, options=CHANNEL_OPTIONS)
        else:
            self._channel = grpc.aio.secure_channel(target, creds, options=CHANNEL_OPTIONS)
        self._stub: Any = pb_grpc.PracStub(self._channel)  # type: ignore[no-untyped-call]
        self._metadata = metadata(token, affinity)
        self.timeout = timeout
        self.target = target
        self.patience = patience

    async def _call(self, rpc: str, request: Any) -> Any:
        try:
            return await getattr(self._stub, rpc)(request, timeout=self.timeout, metadata=self._metadata)
        except grpc.RpcError as e:
            raise errors.from_rpc_error(e, rpc) from None

    async def policies(self) -> list[PolicyInfo]:
        response = await self._call("ListPolicies", pb.ListPoliciesRequest())
        return [PolicyInfo.from_proto(p) for p in response.policies]

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
    ) -> _Opening:
        """`await client.session(...)` or `async with client.session(...) as session`."""
        options = session_options(
            epsilon=epsilon,
            epsilon_coef=epsilon_coef,
            growth=growth,
            max_horizon=max_horizon,
            seed=seed,
            sampled=sampled,
        )
        return _Opening(self, pb.OpenSessionRequest(policy=policy, options=options))

    async def close(self) -> None:
        await self._channel.close(grace=None)

    async def __aenter__(self) -> Client:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


class _Opening:
    """An OpenSession in flight: awaitable, or an async context manager that closes the session."""

    def __init__(self, client: Client, request: pb.OpenSessionRequest) -> None:
        self._client = client
        self._request = request
        self._session: Session | None = None

    async def _open(self) -> Session:
        opened = await self._client._call("OpenSession", self._request)
        return Session(self._client, opened, self._request.policy)

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


class Session:
    def __init__(self, client: Client, opened: pb.OpenSessionResponse, policy: str) -> None:
        self._client = client
        self.id: str = opened.session_id
        self.policy = PolicyInfo.from_proto(opened.policy)
        self.options = SessionOptions.from_proto(opened.options)
        self._stream: Any = None
        self._new_episode = False
        self.closed = False
        self._policy_name = policy
        self._options_in_force = _resume.options_in_force(opened.options)
        self._held: pb.Plan | None = None
        self.resumes = 0
        """Times the session was re-opened with its plan on a server that did not know it."""

    async def step(self, observation: ArrayLike, *, new_episode: bool = False) -> StepResult:
        """As `prac_client.Session.step`, resuming the same way."""
        if self.closed:
            raise errors.SessionNotFound(
                f"session '{self.id}' was closed by this client; open a new one with client.session(...)"
            )
        observed = observation_list(observation)
        new_episode = new_episode or self._new_episode
        loop = asyncio.get_running_loop()
        give_up = loop.time() + self._client.patience
        while True:
            request = pb.StepRequest(session_id=self.id, observation=observed, new_episode=new_episode)
            try:
                response = await self._send(request)
            except _resume.RESUMABLE:
                if loop.time() > give_up:
                    raise
                recovered = await self._recover()
                if recovered is None:
                    continue
                response = recovered
            self._held = _resume.held_plan(response)
            self._new_episode = False
            return StepResult.from_proto(response, self.policy.act_dim, self.policy.obs_dim)

    async def _recover(self) -> pb.StepResponse | None:
        try:
            now = await self._client._call("GetPlan", pb.GetPlanRequest(session_id=self.id))
        except (errors.SessionNotFound, errors.SessionExpired):
            await self._reopen()
            return None
        except errors.ServerUnavailable:
            await asyncio.sleep(_resume.RETRY_PAUSE)
            return None
        if _resume.applied(self._held, now):
            return _resume.answer_from_plan(self._held, now)
        return None

    async def _reopen(self) -> None:
        request = pb.OpenSessionRequest(policy=self._policy_name, options=self._options_in_force)
        if self._held is not None:
            request.resume.CopyFrom(self._held)
        try:
            opened = await self._client._call("OpenSession", request)
        except errors.ServerUnavailable:
            await asyncio.sleep(_resume.RETRY_PAUSE)
            return
        self.id = opened.session_id
        self.resumes += 1

    async def _send(self, request: pb.StepRequest) -> Any:
        if self._stream is None:
            self._stream = self._client._stub.StepStream(metadata=self._client._metadata)
        stream = self._stream
        try:
            await stream.write(request)
            response = await asyncio.wait_for(stream.read(), self._client.timeout)
            if response is EOF:
                code = await stream.code()
                details = await stream.details()
                raise errors.from_rpc_error(_Status(code, details), "Step")
        except grpc.RpcError as e:
            self._drop_stream()
            raise errors.from_rpc_error(e, "Step") from None
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

    async def reset(self, observation: ArrayLike | None = None) -> StepResult | None:
        if observation is None:
            self._new_episode = True
            return None
        return await self.step(observation, new_episode=True)

    async def plan(self) -> Plan:
        p = await self._client._call("GetPlan", pb.GetPlanRequest(session_id=self.id))
        return Plan.from_proto(p, self.policy.act_dim, self.policy.obs_dim)

    async def watch(self) -> AsyncIterator[Plan]:
        call = self._client._stub.WatchPlan(pb.WatchPlanRequest(session_id=self.id), metadata=self._client._metadata)
        try:
            async for p in call:
                yield Plan.from_proto(p, self.policy.act_dim, self.policy.obs_dim)
        except grpc.RpcError as e:
            raise errors.from_rpc_error(e, "WatchPlan") from None
        finally:
            call.cancel()

    async def close(self) -> int:
        if self._stream is not None:
            try:
                await self._stream.done_writing()
            except grpc.RpcError:
                pass
            self._drop_stream()
        if self.closed:
            return 0
        self.closed = True
        response = await self._client._call("CloseSession", pb.CloseSessionRequest(session_id=self.id))
        return int(response.steps)

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
