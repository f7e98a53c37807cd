"""Channel settings shared by the sync and asyncio clients."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Literal, Sequence

import grpc


@dataclass(frozen=True)
class TlsConfig:
    """TLS for the channel: PEM bytes; all None means the system's root certificates."""

    root_certificates: bytes | None = None
    private_key: bytes | None = None
    certificate_chain: bytes | None = None

    def credentials(self) -> grpc.ChannelCredentials:
        return grpc.ssl_channel_credentials(self.root_certificates, self.private_key, self.certificate_chain)


Tls = TlsConfig | grpc.ChannelCredentials | bool | None

# Generous limits; the server enforces its own (--max-message-bytes). A server that restarts is
# tried again within 0.1-1 s (gRPC's default backoff starts at 1 s and grows to 120 s), so a
# session resumes soon after it is back.
CHANNEL_OPTIONS: Sequence[tuple[str, int]] = (
    ("grpc.max_receive_message_length", 64 << 20),
    ("grpc.max_send_message_length", 64 << 20),
    ("grpc.initial_reconnect_backoff_ms", 100),
    ("grpc.min_reconnect_backoff_ms", 100),
    ("grpc.max_reconnect_backoff_ms", 1000),
)


def credentials(tls: Tls) -> grpc.ChannelCredentials | None:
    """None for a plaintext channel."""
    if tls is None or tls is False:
        return None
    if tls is True:
        return grpc.ssl_channel_credentials()
    if isinstance(tls, TlsConfig):
        return tls.credentials()
    return tls


AFFINITY_HEADER = "x-prac-affinity"
"""The metadata key an affinity proxy (deploy/haproxy, deploy/nginx) hashes, and the client's own
ring hash with balance="ring_hash"."""

Balance = Literal["pick_first", "round_robin", "ring_hash"]

RING_HASH_SWITCH = "GRPC_EXPERIMENTAL_RING_HASH_SET_REQUEST_HASH_KEY"
"""gRPC C-core (grpcio 1.85) reads ring_hash's requestHashHeader (gRFC A76) only while this
environment variable is true; without it every call fails with "hash attribute not present"."""


def service_config(balance: Balance) -> dict[str, object]:
    """The channel's service config for a load-balancing policy over the addresses the target
    resolves to. "ring_hash" hashes each call's x-prac-affinity header onto a ring of the
    addresses (gRFC A76), so a client's calls stay on one server while it is reachable, and when
    it is not, go to the next one on the ring: only that server's clients move."""
    if balance == "ring_hash":
        switch = os.environ.setdefault(RING_HASH_SWITCH, "true")
        if switch.strip().lower() not in ("1", "true", "yes"):
            raise ValueError(f'balance="ring_hash" needs {RING_HASH_SWITCH}=true, not {switch!r}')
        return {"loadBalancingConfig": [{"ring_hash_experimental": {"requestHashHeader": AFFINITY_HEADER}}]}
    if balance in ("pick_first", "round_robin"):
        return {"loadBalancingConfig": [{balance: {}}]}
    raise ValueError(f"balance {balance!r}: expected 'pick_first', 'round_robin' or 'ring_hash'")


def channel_options(
    balance: Balance | None, authority: str | None, affinity: str | None
) -> list[tuple[str, str | int]]:
    """CHANNEL_OPTIONS with the balancing policy and the authority (the name a TLS certificate
    is checked against, and HTTP/2's :authority), which a target that lists addresses
    (ipv4:10.0.0.1:50051,10.0.0.2:50051) needs: its own is not a valid host name."""
    options: list[tuple[str, str | int]] = list(CHANNEL_OPTIONS)
    if balance is not None:
        if balance == "ring_hash" and not affinity:
            raise ValueError('balance="ring_hash" hashes the affinity key: give affinity=')
        options.append(("grpc.service_config", json.dumps(service_config(balance))))
    if authority is not None:
        options.append(("grpc.default_authority", authority))
    return options


def metadata(token: str | None, affinity: str | None = None) -> tuple[tuple[str, str], ...]:
    """Call metadata: the bearer token (servers with auth enabled check it) and the affinity key
    (a proxy such as deploy/nginx keeps a client's calls on one replica by it)."""
    entries: list[tuple[str, str]] = []
    if token:
        entries.append(("authorization", f"Bearer {token}"))
    if affinity:
        entries.append((AFFINITY_HEADER, affinity))
    return tuple(entries)
