"""The affinity proxy as deploy/k8s/overlays/haproxy runs it: the image `scripts/proxy-image
build` makes, with deploy/haproxy/haproxy.cfg (its DNS-discovered servers replaced by the test's
two replicas), locked down as prac's containers are, TLS on both sides. Needs podman and haproxy
(skipped without them, unless PRAC_REQUIRE_DEPLOY is set)."""

from __future__ import annotations

import collections
import dataclasses
import json
import pathlib
import re
import shutil
import subprocess
import threading
import time
import urllib.error
import urllib.request
import uuid
from typing import Callable, Iterator

import numpy as np
import pytest

import prac_client
from prac_client import Client, StepResult, _client, _resume, errors
from prac_client._proto.prac.v1 import prac_pb2 as pb

from conftest import REPO
from deploy_support import SERVING, Container, built_images, free_port, tool, version, wait_health, world_readable_dir

PROXY_CONFIG = REPO / "deploy" / "haproxy" / "haproxy.cfg"
# A wide tolerance keeps every plan, so each step executes the action committed for it.
KEEP_ALL = {"epsilon": 1e6, "max_horizon": 16}
ROBOTS = 16
# Seconds between a robot's steps.
PACE = 0.02


@pytest.fixture(scope="module")
def images() -> dict[str, str]:
    return built_images()


@pytest.fixture(scope="module")
def proxy_image() -> str:
    tool("podman")
    tool("haproxy")
    result = subprocess.run([str(REPO / "scripts" / "proxy-image"), "build"], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    print(result.stdout.strip().splitlines()[-1])
    return f"prac-haproxy:{version()}"


@pytest.fixture
def scratch() -> Iterator[pathlib.Path]:
    """A folder the containers' user (65532) can read: certificates and configs."""
    path = world_readable_dir("prac-proxy-test")
    yield path
    shutil.rmtree(path, ignore_errors=True)


def openssl(*args: str) -> None:
    subprocess.run([tool("openssl"), *args], check=True, capture_output=True)


def certificates(scratch: pathlib.Path) -> pathlib.Path:
    """As a prac-tls Secret holds them: tls.crt and tls.key, signed by the CA in ca.crt, for the
    names the replicas are reached by (prac-headless) and the proxy (prac-affinity, localhost)."""
    tls = scratch / "tls"
    tls.mkdir(mode=0o755)
    ca_key = scratch / "ca.key"
    ec = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes")
    openssl("req", "-x509", *ec, "-keyout", str(ca_key), "-out", str(tls / "ca.crt"), "-days", "1", "-subj", "/CN=prac-test-ca")
    openssl("req", *ec, "-keyout", str(tls / "tls.key"), "-out", str(scratch / "tls.csr"), "-subj", "/CN=prac")
    (scratch / "ext").write_text(
        "subjectAltName=DNS:prac-headless,DNS:prac-affinity,DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth\n"
    )
    openssl("x509", "-req", "-in", str(scratch / "tls.csr"), "-CA", str(tls / "ca.crt"), "-CAkey", str(ca_key),
            "-CAcreateserial", "-out", str(tls / "tls.crt"), "-days", "1", "-extfile", str(scratch / "ext"))
    for f in tls.iterdir():
        f.chmod(0o644)
    ca_key.unlink()
    return tls


def proxy_config(replicas: list[str]) -> str:
    """deploy/haproxy/haproxy.cfg with its server-template (the headless Service's DNS) replaced
    by a server line per replica address, in the same slots: nothing else changes."""
    servers = "\n".join(f"    server prac{k + 1} {address}:50051" for k, address in enumerate(replicas))
    text, n = re.subn(r"^ *server-template .*$", servers, PROXY_CONFIG.read_text(), flags=re.MULTILINE)
    assert n == 1
    return text


class Proxy:
    """`podman run` of the proxy image, locked down as prac's: read-only root, no capabilities,
    uid 65532; gRPC and the probe port published on loopback."""

    def __init__(self, image: str, config: pathlib.Path, tls: pathlib.Path) -> None:
        self.podman = tool("podman")
        self.name = f"prac-proxy-test-{uuid.uuid4().hex[:10]}"
        self.port, self.probe_port = free_port(), free_port()
        subprocess.run(
            [self.podman, "run", "-d", "--name", self.name,
             "--read-only", "--cap-drop=ALL", "--security-opt", "no-new-privileges", "--user", "65532",
             "-p", f"127.0.0.1:{self.port}:50051", "-p", f"127.0.0.1:{self.probe_port}:8404",
             "-v", f"{config}:/etc/haproxy:ro", "-v", f"{tls}:/var/run/secrets/prac/tls:ro", image],
            check=True, capture_output=True, text=True,
        )

    def get(self, path: str) -> tuple[int, str]:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{self.probe_port}{path}", timeout=2) as r:
                return r.status, r.read().decode()
        except urllib.error.HTTPError as e:
            return e.code, e.read().decode()

    def wait_servers_up(self, count: int, timeout: float = 30) -> None:
        """Until its health checks have `count` replicas up (its Prometheus metrics say)."""
        deadline = time.monotonic() + timeout
        up = None
        while time.monotonic() < deadline:
            try:
                _, metrics = self.get("/metrics")
                found = re.search(r'^haproxy_backend_active_servers\{proxy="prac"\} (\d+)', metrics, re.MULTILINE)
                up = int(found.group(1)) if found else None
                if up == count:
                    return
            except OSError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"{up} replicas up, not {count}, after {timeout} s: {self.logs()[-3000:]}")

    def logs(self) -> str:
        result = subprocess.run([self.podman, "logs", self.name], capture_output=True, text=True)
        return result.stdout + result.stderr

    def stop(self, grace: int) -> float:
        """`podman stop -t grace`: the image's STOPSIGNAL, then SIGKILL after `grace` seconds;
        returns the seconds it took."""
        start = time.monotonic()
        subprocess.run([self.podman, "stop", "-t", str(grace), self.name], check=True, capture_output=True)
        return time.monotonic() - start

    def exit_code(self) -> int:
        out = subprocess.run([self.podman, "inspect", "--format", "{{.State.ExitCode}}", self.name],
                             check=True, capture_output=True, text=True).stdout
        return int(out)

    def remove(self) -> None:
        subprocess.run([self.podman, "rm", "-f", "-t", "0", self.name], capture_output=True)


def container_ip(c: Container) -> str:
    out = subprocess.run([c.podman, "inspect", "--format", "{{.NetworkSettings.IPAddress}}", c.name],
                         check=True, capture_output=True, text=True).stdout.strip()
    assert out, f"{c.name} has no address on podman's network"
    return out


@dataclasses.dataclass
class Robot:
    key: str
    results: list[StepResult] = dataclasses.field(default_factory=list)
    answered: list[float] = dataclasses.field(default_factory=list)
    session: prac_client.Session | None = None
    failed: BaseException | None = None


@dataclasses.dataclass
class Ending:
    """A StepStream that ended, as the client saw it at its next step."""

    robot: str
    at: float
    kind: str
    code: str
    message: str
    # Seconds from sending the step to the error: about 0 where the stream had ended already,
    # between steps.
    waited: float


@pytest.fixture
def record(monkeypatch: pytest.MonkeyPatch) -> tuple[list[Ending], list[tuple[str, float]]]:
    """Every stream that ended with a step in flight, and every such step the replica had applied
    (its answer rebuilt from the session's plan rather than the step sent again)."""
    endings: list[Ending] = []
    applied: list[tuple[str, float]] = []
    step, rebuild = _client._StepStream.step, _resume.answer_from_plan

    def recording_step(self: _client._StepStream, request: pb.StepRequest, timeout: float | None) -> pb.StepResponse:
        sent = time.monotonic()
        try:
            return step(self, request, timeout)
        except errors.PracError as e:
            code = e.code.name if e.code is not None else "CLIENT"
            now = time.monotonic()
            endings.append(Ending(threading.current_thread().name, now, type(e).__name__, code, e.message, now - sent))
            raise

    def recording_rebuild(held: pb.Plan | None, now: pb.Plan) -> pb.StepResponse:
        applied.append((threading.current_thread().name, time.monotonic()))
        return rebuild(held, now)

    monkeypatch.setattr(_client._StepStream, "step", recording_step)
    monkeypatch.setattr(_resume, "answer_from_plan", recording_rebuild)
    return endings, applied


def assert_contiguous(results: list[StepResult]) -> None:
    """One episode's steps 0, 1, ... in order, each executing the action the step before it
    committed for it."""
    for t, r in enumerate(results):
        assert (r.step, r.episode) == (t, 0), (t, r.step, r.episode)
        if t > 0:
            np.testing.assert_allclose(r.action, results[t - 1].forecast_actions[1], atol=1e-5)


def wait_until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def test_sixteen_robots_through_the_proxy_survive_a_killed_replica_and_a_drained_proxy(
    proxy_image: str, images: dict[str, str], scratch: pathlib.Path, record: tuple[list[Ending], list[tuple[str, float]]]
) -> None:
    """Two prac containers behind two proxies (the Deployment's two pods), 16 robots stepping
    through them at once, each with its own affinity key. The replica holding about half the
    sessions is killed (SIGKILL) mid-episode: its robots resume on the other replica, the rest
    do not move. Then one proxy is stopped as Kubernetes stops it (its STOPSIGNAL, SIGUSR1):
    its streams end with a status the client resumes from, and every robot goes on through the
    other proxy, on the same replica. Every robot's steps stay contiguous throughout."""
    endings, applied = record
    tls = certificates(scratch)
    settings = scratch / "prac.toml"
    settings.write_text(
        'tls_cert = "/var/run/secrets/prac/tls/tls.crt"\ntls_key = "/var/run/secrets/prac/tls/tls.key"\n'
    )
    settings.chmod(0o644)
    mounts = (f"{tls}:/var/run/secrets/prac/tls:ro", f"{settings}:/etc/prac/prac.toml:ro")
    started: list[Container | Proxy] = []
    stop = threading.Event()
    threads: list[threading.Thread] = []
    try:
        replicas = [Container(images["bundles"], volumes=mounts) for _ in range(2)]
        started.extend(replicas)
        for r in replicas:
            wait_health(r.health_address, "prac.v1.Prac", SERVING)
        config = scratch / "haproxy"
        config.mkdir(mode=0o755)
        (config / "haproxy.cfg").write_text(proxy_config([container_ip(r) for r in replicas]))
        (config / "haproxy.cfg").chmod(0o644)
        proxies = [Proxy(proxy_image, config, tls) for _ in range(2)]
        started.extend(proxies)
        for p in proxies:
            p.wait_servers_up(2)
            assert p.get("/readyz") == (200, "ready\n")
        # The proxies' Service: a client connects to the first that accepts.
        target = "ipv4:" + ",".join(f"127.0.0.1:{p.port}" for p in proxies)
        trust = prac_client.TlsConfig(root_certificates=(tls / "ca.crt").read_bytes())
        robots = [Robot(f"robot-{k}") for k in range(ROBOTS)]

        def play(robot: Robot, seed: int) -> None:
            rng = np.random.default_rng(seed)
            try:
                with Client(target, tls=trust, timeout=10, affinity=robot.key, authority="localhost") as client:
                    robot.session = client.session("pendulum", **KEEP_ALL)
                    while not stop.is_set():
                        obs = rng.uniform(-1, 1, 3).astype(np.float32)
                        robot.results.append(robot.session.step(obs, new_episode=not robot.results))
                        robot.answered.append(time.monotonic())
                        time.sleep(PACE)
            except BaseException as e:  # reported by the test
                robot.failed = e

        threads = [threading.Thread(target=play, args=(r, k), name=r.key) for k, r in enumerate(robots)]
        for t in threads:
            t.start()
        wait_until(lambda: all(len(r.results) >= 10 or r.failed for r in robots), 30, "robots did not start")

        def holder(session_id: str) -> int:
            for k, r in enumerate(replicas):
                if not r.running():
                    continue
                with Client(f"localhost:{r.grpc_port}", tls=trust, timeout=5) as direct:
                    try:
                        direct._call(direct._stub.GetPlan, pb.GetPlanRequest(session_id=session_id))
                        return k
                    except prac_client.SessionNotFound:
                        pass
            raise AssertionError(f"no replica holds session {session_id}")

        assert all(r.session is not None for r in robots), [r.failed for r in robots]
        before = [holder(r.session.id) for r in robots]  # type: ignore[union-attr]
        split = collections.Counter(before)
        lost = split.most_common(1)[0][0]
        assert 0 < split[lost] < ROBOTS, split
        moved = {r.key for r, h in zip(robots, before) if h == lost}

        # 1. The replica holding the larger share is killed mid-episode.
        killed_at = time.monotonic()
        replicas[lost].signal("KILL")
        kill_took = time.monotonic() - killed_at
        wait_until(lambda: all(sum(t > killed_at + 1 for t in r.answered) >= 10 or r.failed for r in robots), 60,
                   "robots did not go on after the kill")
        resumed_in = {r.key: min(t for t in r.answered if t > killed_at) - killed_at for r in robots if r.key in moved}
        others_gap = max(np.diff([t for t in r.answered if t > killed_at - 1]).max() for r in robots if r.key not in moved)
        resumes_after_kill = {r.key: r.session.resumes for r in robots}  # type: ignore[union-attr]
        survivor = 1 - lost
        after = [holder(r.session.id) for r in robots]  # type: ignore[union-attr]

        # 2. The first proxy, which every robot connected to, is stopped as the kubelet stops it.
        took: list[float] = []
        stopped_at = time.monotonic()
        stopper = threading.Thread(target=lambda: took.append(proxies[0].stop(grace=60)))
        stopper.start()
        # It stays up, answering /readyz 503, for `grace`; then it unbinds (connections refused).
        readiness: list[tuple[float, object]] = []
        while stopper.is_alive():
            try:
                answer: object = proxies[0].get("/readyz")
            except urllib.error.URLError as e:
                answer = type(e.reason).__name__
            except OSError as e:
                answer = type(e).__name__
            if not readiness or readiness[-1][1] != answer:
                readiness.append((time.monotonic() - stopped_at, answer))
            if isinstance(answer, str):
                break
            time.sleep(0.05)
        stopper.join(90)
        wait_until(lambda: all(sum(t > stopped_at + took[0] for t in r.answered) >= 10 or r.failed for r in robots), 30,
                   "robots did not go on after the proxy stopped")
        stop.set()
        for t in threads:
            t.join(30)
        assert not any(t.is_alive() for t in threads)
        failures = {r.key: repr(r.failed) for r in robots if r.failed}
        assert not failures, failures

        # What the measurements say.
        print(f"\nsessions per replica {dict(split)}; replica {lost} killed with {len(moved)} of them")
        print(f"`podman kill -s KILL` took {kill_took:.3f} s")
        print("kill -> next answered step, per moved robot (s): "
              + ", ".join(f"{resumed_in[k]:.3f}" for k in sorted(resumed_in, key=lambda k: int(k.split('-')[1]))))
        print(f"longest gap between steps of the robots that did not move: {others_gap:.3f} s")
        kill_endings = [e for e in endings if killed_at <= e.at < stopped_at]
        stop_endings = [e for e in endings if e.at >= stopped_at]
        print(f"streams ended by the kill: {collections.Counter((e.kind, e.code) for e in kill_endings)}")
        offsets = sorted(e.at - stopped_at for e in stop_endings)
        print("proxy stop: /readyz " + ", ".join(f"{a!r} from {t:.2f} s" for t, a in readiness))
        print(f"proxy stop: podman stop took {took[0]:.2f} s, exit code {proxies[0].exit_code()}; "
              f"{len(stop_endings)} streams ended (the step that met each had waited "
              f"{', '.join(f'{e.waited * 1e3:.1f}' for e in sorted(stop_endings, key=lambda e: e.waited))} ms), "
              f"{offsets[0] if offsets else float('nan'):.2f}-{offsets[-1] if offsets else float('nan'):.2f} s after the signal: "
              f"{collections.Counter((e.kind, e.code, e.message) for e in stop_endings)}")
        applied_at_stop = [a for a in applied if a[1] >= stopped_at]
        print(f"of the steps that met an ended stream, {len(applied_at_stop)} had been applied by the replica "
              f"(answer rebuilt from the plan), {len(stop_endings) - len(applied_at_stop)} were sent again")
        print(f"steps per robot: {min(len(r.results) for r in robots)}-{max(len(r.results) for r in robots)}")

        # The kill: only the lost replica's robots moved, each once, all to the survivor.
        for r, b, a in zip(robots, before, after):
            assert a == survivor, (r.key, b, a)
            assert resumes_after_kill[r.key] == (1 if r.key in moved else 0), (r.key, resumes_after_kill[r.key])
        assert all(e.kind == "ServerUnavailable" for e in kill_endings), kill_endings
        assert {e.robot for e in kill_endings} <= moved, kill_endings
        # The proxy stop: HAProxy drained and left by itself, before podman's SIGKILL.
        logs = proxies[0].logs()
        assert "Grace period expired, proceeding with soft-stop now" in logs, logs[-3000:]
        assert took[0] < 60, took
        # Ready until the signal, then 503 "stopping" through the grace period, then unbound.
        assert readiness[0][1] in ((200, "ready\n"), (503, "stopping\n")), readiness
        assert (503, "stopping\n") in [a for _, a in readiness], readiness
        assert isinstance(readiness[-1][1], str), readiness
        # Every stream it ended under a step ended with a status the client resumes from, each
        # robot's at most once, and none needed a new session: the other proxy hashes every
        # robot to the same replica, which still held its session.
        assert all(e.kind == "ServerUnavailable" for e in stop_endings), stop_endings
        assert max(collections.Counter(e.robot for e in stop_endings).values(), default=0) <= 1, stop_endings
        assert all(r.session.resumes == resumes_after_kill[r.key] for r in robots)  # type: ignore[union-attr]
        for r in robots:
            assert_contiguous(r.results)
    finally:
        stop.set()
        for t in threads:
            t.join(30)
        for c in started:
            c.remove()


def test_the_proxy_image_is_small_non_root_drains_on_stop_and_records_its_packages(proxy_image: str) -> None:
    podman = tool("podman")
    out = subprocess.run([podman, "image", "inspect", proxy_image], check=True, capture_output=True, text=True).stdout
    found = json.loads(out)[0]
    print(f"{proxy_image}: {found['Size'] / 1e6:.1f} MB")
    config = found["Config"]
    assert config["User"] == "65532:65532"
    # podman, docker, containerd and CRI-O stop a container with its image's STOPSIGNAL.
    assert config["StopSignal"] == "SIGUSR1"
    assert config["Entrypoint"] == ["/usr/sbin/haproxy", "-f", "/etc/haproxy/haproxy.cfg"]
    # It runs as it is: every library it links against is in the image.
    about = subprocess.run(
        [podman, "run", "--rm", "--read-only", "--cap-drop=ALL", "--entrypoint", "/usr/sbin/haproxy", proxy_image, "-vv"],
        check=True, capture_output=True, text=True,
    ).stdout
    assert "Running on OpenSSL version" in about and "Built with the Prometheus exporter" in about, about
    # With the records of the Debian packages they come from, as scanners read them.
    if shutil.which("dpkg-query"):
        records = REPO / "target" / "proxy-image" / "context" / "rootfs" / "var" / "lib" / "dpkg" / "status.d"
        packages = {p.name for p in records.iterdir()}
        assert {"haproxy", "libc6", "libssl3", "libpcre2-8-0", "liblua5.3-0"} <= packages, packages


def test_haproxy_accepts_the_config_kubernetes_mounts(tmp_path: pathlib.Path) -> None:
    """`haproxy -c` with warnings as errors, on the config as the ConfigMap holds it (DNS
    discovery, resolvers and all), with certificates where the Secret is mounted."""
    haproxy = tool("haproxy")
    tls = certificates(tmp_path)
    config = tmp_path / "haproxy.cfg"
    config.write_text(PROXY_CONFIG.read_text().replace("/var/run/secrets/prac/tls", str(tls)))
    result = subprocess.run(
        [haproxy, "-c", "-dW", "-f", str(config)], capture_output=True, text=True,
        env={"POD_NAMESPACE": "prac", "CLUSTER_DOMAIN": "cluster.local", "PATH": "/usr/sbin:/usr/bin"},
    )
    assert result.returncode == 0, result.stdout + result.stderr
