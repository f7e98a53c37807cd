"""Channel settings shared by the sync and asyncio clients."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

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
"""The metadata key an affinity proxy (deploy/nginx, deploy/k8s/overlays/envoy) hashes."""


def metadata(token: str | None, affinity: str | None = None) -> tuple[tuple[str, str], ...]:
    """Call metadata: the bearer token (servers with auth enabled check it) and the affinity key
    (a proxy such as deploy/nginx keeps a client's calls on one replica by it)."""
    entries: list[tuple[str, str]] = []
    if token:
        entries.append(("authorization", f"Bearer {token}"))
    if affinity:
        entries.append((AFFINITY_HEADER, affinity))
    return tuple(entries)
