"""Fixtures: bundles written by test code and a real `prac serve` on a free port."""

from __future__ import annotations

import os
import pathlib
import signal
import subprocess
import time
from typing import Any, Callable, Iterator

import numpy as np
import pytest

from prac_client import Client, ServerUnavailable, TlsConfig
from prac_client.bundle import from_sb3_state_dict, random_model, random_sb3_state_dict, write_bundle

REPO = pathlib.Path(__file__).resolve().parents[3]


def prac_bin() -> str:
    """PRAC_BIN, else the repository's debug build (built if missing)."""
    if "PRAC_BIN" in os.environ:
        return os.environ["PRAC_BIN"]
    path = REPO / "target" / "debug" / "prac"
    if not path.exists():
        subprocess.run(["cargo", "build", "--bin", "prac"], cwd=REPO, check=True)
    return str(path)


def write_toy_bundle(
    directory: pathlib.Path,
    name: str = "pendulum",
    *,
    model: bool = True,
    seed: int = 1,
    layer_norm: bool = False,
    obs_bounds: tuple[list[float], list[float]] | None = None,
    default_guard: dict[str, Any] | None = None,
) -> pathlib.Path:
    """A random Pendulum-shaped policy: obs 3, act 1 in [-2, 2], value scale (10, -10); with
    `layer_norm`, its critics normalise each hidden layer (with_layer_norm_critics); with
    `obs_bounds` (low, high), its forecasts are kept inside them; with `default_guard`
    ({"every_critic": .., "support_limit": ..}), sessions that set no guard get it (format 5)."""
    state = random_sb3_state_dict(3, 1, [32, 32], seed=seed)
    tensors, manifest = from_sb3_state_dict(
        state,
        name=name,
        domain="pendulum",
        action_low=[-2.0],
        action_high=[2.0],
        gamma=0.98,
        value_scale=(10.0, -10.0),
        model=random_model(3, 1, [16, 16], seed=seed) if model else None,
        obs_bounds=obs_bounds,
    )
    if layer_norm:
        tensors, manifest = with_layer_norm_critics(dict(tensors), dict(manifest))
    if default_guard is not None:
        version = 6 if default_guard.get("max_epsilon_coef") else 5
        manifest = {**manifest, "format_version": version, "default_guard": default_guard}
    path = directory / f"{name}.safetensors"
    write_bundle(path, tensors, manifest)
    return path


def with_layer_norm_critics(tensors: dict[str, Any], manifest: dict[str, Any], *, seed: int = 2) -> tuple[dict[str, Any], dict[str, Any]]:
    """The same bundle with a layer norm after each of its critics' hidden layers, in PyTorch's
    nn.Sequential(Linear, LayerNorm, act, ...) layout: linear layer i at 3i, its norm at 3i + 1."""
    rng = np.random.default_rng(seed)
    hidden = manifest["critic"]["hidden"]
    out = {k: v for k, v in tensors.items() if not k.startswith("critic.")}
    for k in range(manifest["critic"]["n_critics"]):
        for i in range(len(hidden) + 1):
            for part in ("weight", "bias"):
                out[f"critic.qf{k}.{3 * i}.{part}"] = tensors[f"critic.qf{k}.{2 * i}.{part}"]
        for i, width in enumerate(hidden):
            out[f"critic.qf{k}.{3 * i + 1}.weight"] = rng.uniform(0.5, 1.5, width).astype(np.float32)
            out[f"critic.qf{k}.{3 * i + 1}.bias"] = rng.uniform(-0.3, 0.3, width).astype(np.float32)
    manifest = {**manifest, "format_version": 3, "critic": {**manifest["critic"], "layer_norm": True}}
    return out, manifest


def self_signed(directory: pathlib.Path, days: int = 1) -> tuple[pathlib.Path, pathlib.Path]:
    """A self-signed certificate for localhost (ECDSA P-256) and its key, written into `directory`."""
    cert, key = directory / "cert.pem", directory / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
        + ["-keyout", str(key), "-out", str(cert), "-days", str(days), "-subj", "/CN=localhost"]
        + ["-addext", "subjectAltName=DNS:localhost"],
        check=True,
        capture_output=True,
    )
    return cert, key


class Server:
    def __init__(
        self,
        bundles: pathlib.Path,
        *args: str,
        listen: str = "127.0.0.1:0",
        log: str = "server.log",
        token: str | None = None,
        tls: TlsConfig | None = None,
    ) -> None:
        self.token = token
        self.tls = tls
        self.stderr_path = bundles / log
        self.process = subprocess.Popen(
            [prac_bin(), "serve", "--listen", listen, "--bundles", str(bundles), *args],
            stdout=subprocess.PIPE,
            stderr=open(self.stderr_path, "w"),
            text=True,
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline()
        try:
            if not line.startswith("listening on "):
                raise RuntimeError(f"server did not start: {line!r} {self.stderr_path.read_text()}")
            self.address = line.removeprefix("listening on ").strip()
            self._wait_loaded()
        except BaseException:
            # Nobody else holds this process yet: stop it rather than leak it.
            self.process.kill()
            self.process.wait(10)
            raise

    def _wait_loaded(self) -> None:
        deadline = time.monotonic() + 20
        # A TLS certificate names localhost, not 127.0.0.1.
        target = self.address.replace("127.0.0.1", "localhost") if self.tls else self.address
        with Client(target, timeout=2, token=self.token, tls=self.tls) as client:
            while True:
                try:
                    client.policies()
                    return
                except ServerUnavailable:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.02)

    def pause(self) -> None:
        """SIGSTOP, and wait until the process is really stopped."""
        os.kill(self.process.pid, signal.SIGSTOP)
        stat = pathlib.Path(f"/proc/{self.process.pid}/stat")
        while stat.read_text().split(") ")[1][0] != "T":
            time.sleep(0.01)

    def resume(self) -> None:
        os.kill(self.process.pid, signal.SIGCONT)

    def kill(self) -> None:
        """SIGKILL: no drain, every session lost."""
        self.process.kill()
        self.process.wait(10)

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(10)
        except subprocess.TimeoutExpired:
            self.process.kill()


@pytest.fixture(scope="session")
def bundles(tmp_path_factory: pytest.TempPathFactory) -> pathlib.Path:
    directory = tmp_path_factory.mktemp("bundles")
    write_toy_bundle(directory)
    return directory


@pytest.fixture(scope="session")
def server(bundles: pathlib.Path) -> Iterator[Server]:
    s = Server(bundles)
    yield s
    s.stop()


@pytest.fixture
def start_server(tmp_path: pathlib.Path) -> Iterator[Callable[..., Server]]:
    """Starts a server with extra flags on the toy bundle; stopped after the test."""
    started: list[Server] = []

    def start(*args: str) -> Server:
        write_toy_bundle(tmp_path)
        s = Server(tmp_path, *args)
        started.append(s)
        return s

    yield start
    for s in started:
        s.stop()


@pytest.fixture
def client(server: Server) -> Iterator[Client]:
    with Client(server.address, timeout=10) as c:
        yield c
