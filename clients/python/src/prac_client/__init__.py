"""Python client for prac, the predictable actor-critic (PrAC) control server.

    from prac_client import Client
    with Client("127.0.0.1:50051") as client, client.session("pendulum", epsilon_coef=0.005) as s:
        result = s.step(observation)   # result.action, result.forecast_actions, result.f_t, ...

`prac_client.aio` has the same API over grpc.aio; `prac_client.gym.run_episode` plays a
gymnasium environment with a served policy.
"""

from prac_client._channel import TlsConfig
from prac_client._client import Client, Session
from prac_client.errors import (
    DeadlineExceeded,
    FallbackFailed,
    InvalidObservation,
    InvalidOptions,
    MessageTooLarge,
    Overloaded,
    PermissionDenied,
    PolicyNotFound,
    PracError,
    ServerUnavailable,
    SessionExpired,
    SessionNotFound,
    Unauthenticated,
)
from prac_client.types import Feature, Plan, PlanGuard, PolicyInfo, SessionOptions, StepResult, ValueScale

__all__ = [
    "Client",
    "DeadlineExceeded",
    "FallbackFailed",
    "Feature",
    "InvalidObservation",
    "InvalidOptions",
    "MessageTooLarge",
    "Overloaded",
    "PermissionDenied",
    "Plan",
    "PlanGuard",
    "PolicyInfo",
    "PolicyNotFound",
    "PracError",
    "ServerUnavailable",
    "Session",
    "SessionExpired",
    "SessionNotFound",
    "SessionOptions",
    "StepResult",
    "TlsConfig",
    "Unauthenticated",
    "ValueScale",
]
__version__ = "0.1.0"
