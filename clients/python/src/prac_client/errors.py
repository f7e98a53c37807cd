"""gRPC statuses of the prac server as Python exceptions, carrying the server's message."""

from __future__ import annotations

from typing import TYPE_CHECKING

import grpc

if TYPE_CHECKING:
    from prac_client.types import StepResult


class PracError(Exception):
    """Base of every error the client raises for a failed call."""

    def __init__(self, message: str, code: grpc.StatusCode | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.code = code

    def __str__(self) -> str:
        name = self.code.name if self.code is not None else "CLIENT"
        return f"{name}: {self.message}"


class PolicyNotFound(PracError):
    """OpenSession named a policy the server does not serve."""


class SessionNotFound(PracError):
    """The session id is unknown or the session was closed."""


class SessionExpired(PracError):
    """The server evicted the session after its idle TTL; open a new one."""


class InvalidObservation(PracError):
    """A step's observation has the wrong length or non-finite values."""


class InvalidOptions(PracError):
    """OpenSession's options were refused (e.g. negative epsilon, horizon over the limit)."""


class Overloaded(PracError):
    """The server is at its session cap or otherwise out of capacity; retry later."""


class MessageTooLarge(PracError):
    """A message exceeded the server's size limit."""


class ServerUnavailable(PracError):
    """The server is loading, shutting down or unreachable."""


class DeadlineExceeded(PracError):
    """The call did not finish within the client's timeout."""


class PermissionDenied(PracError):
    """The caller may not use this session or call."""


class Unauthenticated(PracError):
    """The server wants a (valid) bearer token."""


class FallbackFailed(PracError):
    """The on-board fallback cannot be used (files missing or not the server's bundle, shapes
    that do not fit) or failed to replan. `held` is the action the held plan committed for this
    step, when it has one: what the session answered instead (see `Session.step`)."""

    held: StepResult | None = None


# What gRPC's core says, as INTERNAL, when the connection under a call broke (the server died or
# a proxy reset the stream): the server is gone, not wrong.
_BROKEN_TRANSPORT = ("Stream removed", "RST_STREAM", "Internal error from Core", "Socket closed")


def from_rpc_error(error: grpc.RpcError, rpc: str) -> PracError:
    """Maps a failed call of `rpc` (e.g. "OpenSession", "Step") to its exception."""
    code: grpc.StatusCode | None = error.code() if hasattr(error, "code") else None
    details = error.details() if hasattr(error, "details") else None
    message = details or str(error)
    opening = rpc == "OpenSession"
    # The server names its RPC; a Python user opens sessions with client.session(...).
    message = message.replace("with OpenSession", "with client.session(...)")
    kind: type[PracError]
    if code == grpc.StatusCode.NOT_FOUND:
        kind = PolicyNotFound if opening else SessionNotFound
    elif code == grpc.StatusCode.INVALID_ARGUMENT:
        kind = InvalidOptions if opening else InvalidObservation
    elif code == grpc.StatusCode.FAILED_PRECONDITION:
        kind = SessionExpired
    elif code == grpc.StatusCode.RESOURCE_EXHAUSTED:
        kind = Overloaded
    elif code == grpc.StatusCode.OUT_OF_RANGE:
        kind = MessageTooLarge
    elif code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED):
        kind = ServerUnavailable
    elif code == grpc.StatusCode.INTERNAL and any(m in message for m in _BROKEN_TRANSPORT):
        kind = ServerUnavailable
    elif code == grpc.StatusCode.DEADLINE_EXCEEDED:
        kind = DeadlineExceeded
    elif code == grpc.StatusCode.PERMISSION_DENIED:
        kind = PermissionDenied
    elif code == grpc.StatusCode.UNAUTHENTICATED:
        kind = Unauthenticated
    else:
        kind = PracError
    return kind(message, code)
