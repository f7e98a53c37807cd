"""What the deploy tests share: the tools they need (podman, kubectl, promtool, node), the image
that `scripts/container build` makes, containers run from it, and grpc.health.v1 checks."""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import socket
import subprocess
import time
import uuid
from typing import NoReturn

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from conftest import REPO

SERVING = health_pb2.HealthCheckResponse.SERVING
NOT_SERVING = health_pb2.HealthCheckResponse.NOT_SERVING


def version() -> str:
    text = (REPO / "Cargo.toml").read_text()
    found = re.search(r'^version = "([^"]+)"$', text, re.MULTILINE)
    assert found is not None
    return found.group(1)


def missing(name: str, what: str, remedy: str) -> NoReturn:
    """Skips the test for want of `name`, or fails where PRAC_REQUIRE_DEPLOY is set (.ci/run
    provides them all) and PRAC_REQUIRE_DEPLOY_EXCEPT does not name it."""
    excepted = os.environ.get("PRAC_REQUIRE_DEPLOY_EXCEPT", "").split(",")
    required = "PRAC_REQUIRE_DEPLOY" in os.environ and name not in excepted
    assert not required, f"PRAC_REQUIRE_DEPLOY is set but {what}"
    pytest.skip(f"{what}, so this deploy test was skipped ({remedy})")


def tool(name: str) -> str:
    """The tool's path; without it the test is skipped or fails (missing())."""
    path = shutil.which(name) or next((p for p in (f"/usr/sbin/{name}", f"/usr/bin/{name}") if os.path.exists(p)), None)
    if path is None:
        missing(name, f"{name} is not installed", ".ci/run installs it")
    return path


SCHEMA_CHECK = REPO / "deploy" / "k8s" / "schema-check"


def schema_check() -> list[str]:
    """The command that checks custom resources against their operators' schemas
    (deploy/k8s/schema-check/validate.mjs): it needs node and the folder's npm packages, which
    scripts/test installs there (`npm ci`) where npm is."""
    node = tool("node")
    if not (SCHEMA_CHECK / "node_modules").is_dir():
        missing("schema-check", f"{SCHEMA_CHECK.relative_to(REPO)}/node_modules is missing",
                f"npm ci --prefix {SCHEMA_CHECK.relative_to(REPO)} installs it; scripts/test does")
    return [node, str(SCHEMA_CHECK / "validate.mjs")]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def health(address: str, service: str, timeout: float = 2.0) -> int:
    """grpc.health.v1 Check of `service` at `address` (plaintext)."""
    with grpc.insecure_channel(address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        response = stub.Check(health_pb2.HealthCheckRequest(service=service), timeout=timeout)
        status: int = response.status
        return status


def wait_health(address: str, service: str, status: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    last: object = None
    while time.monotonic() < deadline:
        try:
            last = health(address, service)
            if last == status:
                return
        except grpc.RpcError as e:
            last = e.code()
        time.sleep(0.1)
    raise AssertionError(f"{service!r} at {address}: {last}, not {status}, after {timeout} s")


def world_readable_dir(prefix: str) -> pathlib.Path:
    """A folder the container's user (65532) can read, unlike pytest's 0700 tmp_path."""
    path = pathlib.Path(f"/tmp/{prefix}-{uuid.uuid4().hex[:8]}")
    path.mkdir(mode=0o755)
    path.chmod(0o755)
    return path


class Container:
    """`podman run` of a prac image, locked down as the docs say to run it: read-only root,
    no capabilities, uid 65532, the three ports published on loopback."""

    def __init__(
        self,
        image: str,
        *args: str,
        volumes: tuple[str, ...] = (),
        entrypoint: str | None = None,
        wait_listening: bool = True,
        options: tuple[str, ...] = (),
    ) -> None:
        self.podman = tool("podman")
        self.name = f"prac-test-{uuid.uuid4().hex[:10]}"
        self.grpc_port, self.health_port, self.metrics_port = free_port(), free_port(), free_port()
        command = [
            self.podman, "run", "-d", "--name", self.name,
            "--read-only", "--cap-drop=ALL", "--security-opt", "no-new-privileges", "--user", "65532",
            "-p", f"127.0.0.1:{self.grpc_port}:50051",
            "-p", f"127.0.0.1:{self.health_port}:8081",
            "-p", f"127.0.0.1:{self.metrics_port}:9090",
        ]
        for volume in volumes:
            command += ["-v", volume]
        if entrypoint is not None:
            command += ["--entrypoint", entrypoint]
        command += list(options)
        subprocess.run([*command, image, *args], check=True, capture_output=True, text=True)
        if wait_listening:
            deadline = time.monotonic() + 30
            while "listening on" not in self.logs():
                assert self.running(), f"container exited: {self.logs()}"
                assert time.monotonic() < deadline, f"no 'listening on' in 30 s: {self.logs()}"
                time.sleep(0.05)

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.grpc_port}"

    @property
    def health_address(self) -> str:
        return f"127.0.0.1:{self.health_port}"

    def logs(self) -> str:
        result = subprocess.run([self.podman, "logs", self.name], capture_output=True, text=True)
        return result.stdout + result.stderr

    def state(self) -> tuple[str, int]:
        out = subprocess.run(
            [self.podman, "inspect", "--format", "{{.State.Status}} {{.State.ExitCode}}", self.name],
            check=True, capture_output=True, text=True,
        ).stdout.split()
        return out[0], int(out[1])

    def running(self) -> bool:
        return self.state()[0] == "running"

    def wait_exit(self, timeout: float = 30.0) -> int:
        deadline = time.monotonic() + timeout
        while self.running():
            assert time.monotonic() < deadline, f"still running after {timeout} s: {self.logs()}"
            time.sleep(0.05)
        return self.state()[1]

    def signal(self, name: str) -> None:
        subprocess.run([self.podman, "kill", "-s", name, self.name], check=True, capture_output=True)

    def stop(self, grace: int) -> float:
        """`podman stop -t grace`; returns the seconds it took."""
        start = time.monotonic()
        subprocess.run([self.podman, "stop", "-t", str(grace), self.name], check=True, capture_output=True)
        return time.monotonic() - start

    def remove(self) -> None:
        subprocess.run([self.podman, "rm", "-f", "-t", "0", self.name], capture_output=True)


_built: dict[str, str] = {}


def built_images() -> dict[str, str]:
    """`scripts/container build --with-bundles`, once per test run: {"bare": tag, "bundles": tag}.
    PRAC_IMAGES_BUILT=1 uses the images already built (after `scripts/container build
    --with-bundles`), to rerun container tests without a cargo build."""
    if not _built and os.environ.get("PRAC_IMAGES_BUILT") == "1":
        _built.update(bare=f"prac:{version()}", bundles=f"prac:{version()}-bundles")
    if not _built:
        tool("podman")
        result = subprocess.run(
            [str(REPO / "scripts" / "container"), "build", "--with-bundles"],
            cwd=REPO, capture_output=True, text=True,
        )
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        # The sizes it prints, for the test log.
        print("\n".join(line for line in result.stdout.splitlines() if line.startswith("prac:")))
        _built.update(bare=f"prac:{version()}", bundles=f"prac:{version()}-bundles")
    return _built
