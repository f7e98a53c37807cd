"""The container image as users run it (docs/deploy.md): built by `scripts/container build`, run
by podman with a read-only root, no capabilities and uid 65532. Needs podman (skipped without it,
unless PRAC_REQUIRE_DEPLOY is set)."""

from __future__ import annotations

import io
import json
import os
import pathlib
import re
import shutil
import subprocess
import tarfile
import threading
import time
import tomllib
import urllib.request
from typing import Any, Iterator

import grpc
import numpy as np
import pytest
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from conftest import REPO, self_signed
from deploy_support import NOT_SERVING, SERVING, Container, built_images, free_port, health, tool, wait_health, world_readable_dir
from prac_client import Client, TlsConfig
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client._proto.prac.v1 import prac_pb2_grpc as pb_grpc

SHIPPED = REPO / "bundles"
MAX_BARE_IMAGE_BYTES = 40_000_000


@pytest.fixture(scope="module")
def images() -> dict[str, str]:
    return built_images()


@pytest.fixture
def containers() -> Iterator[list[Container]]:
    started: list[Container] = []
    yield started
    for c in started:
        c.remove()


@pytest.fixture
def bundle_dir() -> Iterator[pathlib.Path]:
    path = world_readable_dir("prac-bundles")
    yield path
    shutil.rmtree(path, ignore_errors=True)


def podman_inspect(image: str) -> dict[str, object]:
    out = subprocess.run([tool("podman"), "image", "inspect", image], check=True, capture_output=True, text=True).stdout
    found: dict[str, object] = json.loads(out)[0]
    return found


def test_the_bare_image_is_small_non_root_and_runs_prac_serve(images: dict[str, str]) -> None:
    bare = podman_inspect(images["bare"])
    size = bare["Size"]
    assert isinstance(size, int)
    print(f"{images['bare']}: {size / 1e6:.1f} MB; {images['bundles']}: {podman_inspect(images['bundles'])['Size'] / 1e6:.1f} MB")  # type: ignore[operator]
    assert size <= MAX_BARE_IMAGE_BYTES, f"{size} bytes"
    config = bare["Config"]
    assert isinstance(config, dict)
    assert config["User"] == "65532:65532"
    assert config["Entrypoint"][:2] == ["/usr/local/bin/prac", "serve"]
    entry = " ".join(config["Entrypoint"])
    for flag in ("--listen 0.0.0.0:50051", "--metrics-listen 0.0.0.0:9090", "--bundles /bundles", "--health-listen 0.0.0.0:8081"):
        assert flag in entry, entry
    # Serving only: the training and picture subcommands are not in it.
    help_text = subprocess.run(
        [tool("podman"), "run", "--rm", "--read-only", "--entrypoint", "/usr/local/bin/prac", images["bare"], "--help"],
        check=True, capture_output=True, text=True,
    ).stdout
    commands = set(re.findall(r"^  ([a-z-]+) ", help_text, re.MULTILINE))
    assert {"serve", "copy-bundles", "sleep"} <= commands, commands
    assert not commands & {"train", "fit-model", "bench-train", "render"}, commands


def test_the_images_carry_their_source_revision_and_a_list_of_their_rust_crates(images: dict[str, str]) -> None:
    cargo = tomllib.loads((REPO / "Cargo.toml").read_text())["package"]
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    for image in images.values():
        labels = podman_inspect(image)["Labels"]
        assert isinstance(labels, dict)
        assert labels["org.opencontainers.image.source"] == cargo["repository"]
        assert re.fullmatch(r"[0-9a-f]{40}", labels["org.opencontainers.image.revision"]), labels
        assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ", labels["org.opencontainers.image.created"]), labels
        if head:
            print(f"{image}: revision {labels['org.opencontainers.image.revision'][:12]} (HEAD {head[:12]})")
    # The SBOM inside the image: the crates of the serving-only build, not the training ones.
    podman = tool("podman")
    name = f"prac-sbom-{free_port()}"
    subprocess.run([podman, "create", "--name", name, images["bare"]], check=True, capture_output=True)
    try:
        text = subprocess.run([podman, "cp", f"{name}:/usr/share/doc/prac/sbom.cdx.json", "-"], check=True, capture_output=True).stdout
        records = subprocess.run([podman, "cp", f"{name}:/var/lib/dpkg/status.d", "-"], check=True, capture_output=True).stdout
    finally:
        subprocess.run([podman, "rm", "-f", name], capture_output=True)
    # The C libraries' Debian packages, as scanners read them.
    with tarfile.open(fileobj=io.BytesIO(records)) as archive:
        packages = {pathlib.PurePath(m.name).name for m in archive.getmembers() if m.isfile()}
    assert {"libc6", "libgcc-s1"} <= packages, packages
    with tarfile.open(fileobj=io.BytesIO(text)) as archive:
        member = archive.extractfile("sbom.cdx.json")
        assert member is not None
        sbom = json.load(member)
    beside = json.loads((REPO / "target" / "container" / f"prac-{cargo['version']}.cdx.json").read_text())
    assert sbom == beside
    assert sbom["bomFormat"] == "CycloneDX" and sbom["metadata"]["component"]["name"] == "prac"
    crates = {c["name"]: c["version"] for c in sbom["components"]}
    lock = {p["name"]: p["version"] for p in tomllib.loads((REPO / "Cargo.lock").read_text())["package"]}
    for crate in ("tonic", "tokio", "rustls", "safetensors", "prost"):
        assert crates[crate] == lock[crate], crate
    assert "burn" not in crates and "plotters" not in crates, "training and rendering are not in the image"
    print(f"SBOM: {len(crates)} crates, CycloneDX {sbom['specVersion']}")


def test_a_locked_down_container_serves_health_reflection_and_a_session(images: dict[str, str], containers: list[Container]) -> None:
    c = Container(images["bundles"])
    containers.append(c)
    wait_health(c.health_address, "prac.v1.Prac", SERVING)
    # Health on both ports: the plaintext probe port and the main one.
    for address in (c.health_address, c.address):
        for service in ("", "prac.v1.Prac", "liveness"):
            assert health(address, service) == SERVING, (address, service)
    # The probe port answers grpc.health.v1 alone.
    with grpc.insecure_channel(c.health_address) as channel:
        with pytest.raises(grpc.RpcError) as refused:
            pb_grpc.PracStub(channel).ListPolicies(pb.ListPoliciesRequest(), timeout=5)
        assert refused.value.code() == grpc.StatusCode.UNIMPLEMENTED
    with grpc.insecure_channel(c.address) as channel:
        services = set(ProtoReflectionDescriptorDatabase(channel).get_services())
        assert {"prac.v1.Prac", "grpc.health.v1.Health"} <= services, services
    with Client(c.address, timeout=10) as client:
        assert {p.name for p in client.policies()} == {p.stem for p in SHIPPED.glob("*.safetensors")}
        with client.session("pendulum", epsilon_coef=0.01) as session:
            rng = np.random.default_rng(0)
            for t in range(20):
                angle = rng.uniform(-np.pi, np.pi)
                result = session.step([np.cos(angle), np.sin(angle), rng.uniform(-1, 1)], new_episode=t == 0)
                assert result.step == t and result.action.shape == (1,)
                assert len(result.forecast_actions) >= 1
    metrics = urllib.request.urlopen(f"http://127.0.0.1:{c.metrics_port}/metrics", timeout=5).read().decode()
    assert "prac_serving 1" in metrics and 'prac_steps_total{policy="pendulum"} 20' in metrics, metrics
    assert c.running()


def test_sighup_picks_up_a_changed_bundle(images: dict[str, str], containers: list[Container], bundle_dir: pathlib.Path) -> None:
    shutil.copy(SHIPPED / "pendulum.safetensors", bundle_dir / "pendulum.safetensors")
    (bundle_dir / "pendulum.safetensors").chmod(0o644)
    c = Container(images["bare"], volumes=(f"{bundle_dir}:/bundles:ro",))
    containers.append(c)
    wait_health(c.health_address, "prac.v1.Prac", SERVING)
    with Client(c.address, timeout=10) as client:
        assert [(p.name, p.obs_dim) for p in client.policies()] == [("pendulum", 3)]
        # A new version of the bundle (here the Lander's policy under the same name), renamed
        # into place, and one more bundle.
        partial = bundle_dir / ".pendulum.partial"
        shutil.copy(SHIPPED / "lander.safetensors", partial)
        partial.chmod(0o644)
        partial.rename(bundle_dir / "pendulum.safetensors")
        shutil.copy(SHIPPED / "hopper.safetensors", bundle_dir / "hopper.safetensors")
        (bundle_dir / "hopper.safetensors").chmod(0o644)
        c.signal("HUP")
        deadline = time.monotonic() + 20
        while sorted((p.name, p.obs_dim) for p in client.policies()) != [("hopper", 15), ("pendulum", 8)]:
            assert time.monotonic() < deadline, client.policies()
            time.sleep(0.1)
    assert c.running(), c.logs()
    assert "reloaded bundles" in c.logs()


def test_podman_stop_drains_open_streams_with_unavailable_within_the_grace_period(images: dict[str, str], containers: list[Container]) -> None:
    c = Container(images["bundles"])
    containers.append(c)
    wait_health(c.health_address, "prac.v1.Prac", SERVING)
    grace = 20
    with grpc.insecure_channel(c.address) as channel:
        stub = pb_grpc.PracStub(channel)
        session = stub.OpenSession(pb.OpenSessionRequest(policy="pendulum"), timeout=10).session_id
        requests: list[pb.StepRequest] = [pb.StepRequest(session_id=session, observation=[1.0, 0.0, 0.0], new_episode=True)]
        more = threading.Event()

        def send() -> Iterator[pb.StepRequest]:
            yield requests[0]
            more.wait(60)

        responses = stub.StepStream(send(), timeout=60)
        assert next(responses).step == 0
        took: list[float] = []
        stopper = threading.Thread(target=lambda: took.append(c.stop(grace)))
        stopper.start()
        with pytest.raises(grpc.RpcError) as ended:
            next(responses)
        more.set()
        stopper.join(grace + 10)
    assert ended.value.code() == grpc.StatusCode.UNAVAILABLE, ended.value
    print(f"podman stop took {took[0]:.2f} s (grace {grace} s)")
    assert took[0] < grace, took
    assert c.state() == ("exited", 0), c.logs()
    assert "shutdown requested: draining" in c.logs()


@pytest.mark.parametrize("volume", ["empty", "unreadable"])
def test_a_bundle_volume_without_bundles_stays_up_and_not_serving(
    volume: str, images: dict[str, str], containers: list[Container], bundle_dir: pathlib.Path
) -> None:
    if volume == "unreadable":
        shutil.copy(SHIPPED / "pendulum.safetensors", bundle_dir / "pendulum.safetensors")
        bundle_dir.chmod(0o700)
    c = Container(images["bare"], volumes=(f"{bundle_dir}:/bundles:ro",))
    containers.append(c)
    wait_health(c.health_address, "liveness", SERVING)
    time.sleep(2)
    assert c.running(), c.logs()
    assert health(c.health_address, "prac.v1.Prac") == NOT_SERVING
    assert health(c.health_address, "liveness") == SERVING
    reason = {"empty": "no bundles loaded", "unreadable": "cannot read bundle directory"}[volume]
    assert reason in c.logs(), c.logs()


def test_a_bad_config_file_exits_naming_the_key(images: dict[str, str], containers: list[Container], bundle_dir: pathlib.Path) -> None:
    config = bundle_dir / "prac.toml"
    config.write_text('max_sessions = "many"\n')
    config.chmod(0o644)
    c = Container(images["bundles"], volumes=(f"{config}:/etc/prac/prac.toml:ro",), wait_listening=False)
    containers.append(c)
    assert c.wait_exit() != 0
    assert "max_sessions" in c.logs(), c.logs()


def test_health_listen_on_the_main_port_is_refused(images: dict[str, str], containers: list[Container]) -> None:
    c = Container(
        images["bundles"],
        *("serve", "--listen", "0.0.0.0:50051", "--health-listen", "0.0.0.0:50051", "--bundles", "/bundles"),
        entrypoint="/usr/local/bin/prac",
        wait_listening=False,
    )
    containers.append(c)
    assert c.wait_exit() != 0
    assert "health" in c.logs() and "50051" in c.logs(), c.logs()


def test_a_container_killed_mid_episode_behind_the_affinity_proxy_loses_no_step(
    images: dict[str, str], containers: list[Container], tmp_path: pathlib.Path
) -> None:
    """Two containers behind deploy/nginx (a ring of two, hashed on x-prac-affinity, as
    deploy/haproxy hashes it): the one holding the robot's session is killed
    mid-episode, the client resumes on the other from the plan it holds, the steps go on."""
    from test_resume import KILL_AT, assert_contiguous, play_sync, start_nginx

    tool("nginx")
    replicas = [Container(images["bundles"]), Container(images["bundles"])]
    containers.extend(replicas)
    for r in replicas:
        wait_health(r.health_address, "prac.v1.Prac", SERVING)
    prefix = tmp_path / "nginx"
    prefix.mkdir()
    listen = f"127.0.0.1:{free_port()}"
    nginx = start_nginx(prefix, listen, [r.address for r in replicas])
    killed: list[int] = []
    kill_times: list[float] = []

    def holder(session_id: str) -> int:
        for k, r in enumerate(replicas):
            with grpc.insecure_channel(r.address) as channel:
                try:
                    pb_grpc.PracStub(channel).GetPlan(pb.GetPlanRequest(session_id=session_id), timeout=5)
                    return k
                except grpc.RpcError as e:
                    assert e.code() == grpc.StatusCode.NOT_FOUND, e
        raise AssertionError("no replica holds the session")

    def kill_holder(session_id: str) -> None:
        owner = holder(session_id)
        replicas[owner].signal("KILL")
        killed.append(owner)
        kill_times.append(time.monotonic())

    try:
        results, resumes, final_id, answered_at = play_sync(listen, kill_holder)
    finally:
        nginx.terminate()
        nginx.wait(10)
    assert resumes == 1
    print(f"container killed: step {KILL_AT} answered {answered_at[0] - kill_times[0]:.3f} s after the kill")
    assert_contiguous(results)
    survivor = replicas[1 - killed[0]]
    with grpc.insecure_channel(survivor.address) as channel:
        plan = pb_grpc.PracStub(channel).GetPlan(pb.GetPlanRequest(session_id=final_id), timeout=5)
    assert plan.start_step == len(results) - 1


def container_cgroup(c: Container) -> pathlib.Path:
    """The container's memory cgroup on the host (v1's memory controller, else v2)."""
    pid = subprocess.run(
        [tool("podman"), "inspect", "--format", "{{.State.Pid}}", c.name], check=True, capture_output=True, text=True
    ).stdout.strip()
    lines = pathlib.Path(f"/proc/{pid}/cgroup").read_text().splitlines()
    for line in lines:
        _, controllers, path = line.split(":", 2)
        if "memory" in controllers.split(","):
            return pathlib.Path("/sys/fs/cgroup/memory") / path.lstrip("/")
    v2 = next(line.split(":", 2)[2] for line in lines if line.startswith("0::"))
    return pathlib.Path("/sys/fs/cgroup") / v2.lstrip("/")


def oom_kills(cgroup: pathlib.Path) -> int:
    """The kernel's count of OOM kills in the cgroup: memory.events (v2) or memory.oom_control (v1),
    not podman's OOMKilled flag, which podman 4 on cgroup v1 leaves false even for a killed container."""
    for name in ("memory.events", "memory.oom_control"):
        file = cgroup / name
        if file.exists():
            counts = dict(line.split() for line in file.read_text().splitlines())
            return int(counts.get("oom_kill", "0"))
    raise AssertionError(f"no memory.events or memory.oom_control in {cgroup}")


def peak_bytes(cgroup: pathlib.Path) -> int:
    for name in ("memory.peak", "memory.max_usage_in_bytes"):
        if (cgroup / name).exists():
            return int((cgroup / name).read_text())
    return 0


def flood(c: Container, *args: str) -> dict[str, Any]:
    """prac-flood (clients/bench) against the container, on the core the server is not pinned to."""
    flood_bin = pathlib.Path(os.environ.get("PRAC_BIN", REPO / "target" / "release" / "prac")).parent / "prac-flood"
    assert flood_bin.exists(), f"{flood_bin} is not built (cargo build --release)"
    command = [str(flood_bin), "--server", c.address, "--policy", "hopper", *args]
    if (os.cpu_count() or 1) >= 2:
        command = ["taskset", "-c", "1", *command]
    result = subprocess.run(command, capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    report: dict[str, Any] = json.loads(result.stdout)
    return report


# How a flood call may end: shed by the server with RESOURCE_EXHAUSTED, or never processed
# (opened after its connection's GOAWAY, or queued on a connection that closed).
CLEAN_ENDINGS = {"ResourceExhausted", "refused by GOAWAY", "connection closed"}


@pytest.mark.parametrize("memory", ["96m", "256m"])
def test_floods_of_never_started_calls_and_idle_watchers_never_get_the_container_killed(
    images: dict[str, str], containers: list[Container], memory: str
) -> None:
    pin = ("--cpuset-cpus", "0") if (os.cpu_count() or 1) >= 2 else ()
    c = Container(images["bundles"], options=("--memory", memory, *pin))
    containers.append(c)
    wait_health(c.health_address, "prac.v1.Prac", SERVING)
    assert "from=the cgroup's limit" in c.logs(), c.logs()
    cgroup = container_cgroup(c)
    assert oom_kills(cgroup) == 0
    # 176 connections x 250 StepStreams that send only their HEADERS, reopened as they end.
    calls = flood(c, "--connections", "176", "--calls", "250", "--duration", "20s")
    # Watchers of sessions that never step, 20,000 at once, reopened as they end.
    watchers = flood(c, "--connections", "0", "--watchers", "20000", "--duration", "15s")
    peak = peak_bytes(cgroup)
    print(f"--memory {memory}: cgroup peak {peak / 2**20:.1f} MiB; calls {calls['calls_ended']['by_code']}; "
          f"watchers {watchers['watchers_ended']['by_code']}; probe worst {calls['probe_first_answer_ms_max']:.0f} ms "
          f"and {watchers['probe_first_answer_ms_max']:.0f} ms")
    assert c.running(), c.logs()[-3000:]
    assert oom_kills(cgroup) == 0, f"the kernel killed prac in {cgroup}"
    for report, ended in ((calls, "calls_ended"), (watchers, "watchers_ended")):
        codes = report[ended]["by_code"]
        assert codes.get("ResourceExhausted", 0) > 0, report
        assert set(codes) <= CLEAN_ENDINGS, json.dumps(report[ended], indent=1)
        # A well-behaved client opened a session and had its first answer within a second, each time.
        assert report["probes"] > 0 and report["probes_failed"] == 0, report["probe_failures"]
        assert report["probes_over_1s"] == 0, report["probe_first_answer_ms_max"]
        assert report["server_alive_after"]
    metrics = urllib.request.urlopen(f"http://127.0.0.1:{c.metrics_port}/metrics", timeout=5).read().decode()
    for action in ("call_reset", "watcher_reset", "goaway"):
        assert re.search(rf'prac_memory_shed_total{{action="{action}"}} [1-9]', metrics), (action, metrics)
    # Logged once per burst, not per call.
    assert c.logs().count("memory budget past its high-water mark") <= 4, c.logs()[-3000:]


def kubelet_publish(root: pathlib.Path, files: dict[str, bytes], version: int) -> None:
    """Updates a mounted Secret's folder the way kubelet does: the files into a new
    timestamped folder, then the `..data` symlink renamed onto it, so every name switches at once."""
    folder = root / f"..2026_12_07_00_00_{version:02d}.{version}"
    folder.mkdir(mode=0o755)
    folder.chmod(0o755)
    for name, data in files.items():
        (folder / name).write_bytes(data)
        (folder / name).chmod(0o644)
        if not (root / name).is_symlink():
            (root / name).symlink_to(f"..data/{name}")
    (root / "..data_tmp").symlink_to(folder.name)
    (root / "..data_tmp").rename(root / "..data")


def credential_reloads(c: Container, file: str, result: str) -> float:
    text = urllib.request.urlopen(f"http://127.0.0.1:{c.metrics_port}/metrics", timeout=5).read().decode()
    prefix = f'prac_credential_reloads_total{{file="{file}",result="{result}"}} '
    return next((float(line.removeprefix(prefix)) for line in text.splitlines() if line.startswith(prefix)), 0.0)


def wait_reloads(c: Container, file: str, result: str, count: float) -> None:
    deadline = time.monotonic() + 20
    while credential_reloads(c, file, result) < count:
        assert time.monotonic() < deadline, c.logs()
        time.sleep(0.2)


def test_a_renewed_secret_swapped_in_by_kubelet_is_served_without_a_restart(images: dict[str, str], containers: list[Container], tmp_path: pathlib.Path) -> None:
    """The certificate and tokens in a folder mounted read-only, swapped through `..data` as
    kubelet swaps a renewed Secret: new connections get the new certificate, the open session's
    stream goes on, the dropped token is refused, and garbage keeps the renewed one."""
    secret = world_readable_dir("prac-secret")
    certs = []
    for k in range(2):
        (tmp_path / str(k)).mkdir()
        certs.append(tuple(p.read_bytes() for p in self_signed(tmp_path / str(k), days=30)))
    old_token, new_token = "old-token-0123456789", "new-token-0123456789"
    kubelet_publish(secret, {"tls.crt": certs[0][0], "tls.key": certs[0][1], "tokens": f"{old_token}\n{new_token}\n".encode()}, 1)
    mounted = "/var/run/secrets/prac/tls"
    c = Container(
        images["bundles"],
        "--tls-cert", f"{mounted}/tls.crt", "--tls-key", f"{mounted}/tls.key", "--auth-tokens", f"{mounted}/tokens",
        volumes=(f"{secret}:{mounted}:ro",),
    )
    containers.append(c)
    wait_health(c.health_address, "prac.v1.Prac", SERVING)
    target = f"localhost:{c.grpc_port}"
    try:
        with Client(target, timeout=10, token=old_token, tls=TlsConfig(root_certificates=certs[0][0])) as client:
            with client.session("pendulum", epsilon_coef=0.01) as session:
                for t in range(5):
                    assert session.step([1.0, 0.0, 0.1 * t], new_episode=t == 0).step == t
                kubelet_publish(secret, {"tls.crt": certs[1][0], "tls.key": certs[1][1], "tokens": f"{new_token}\n".encode()}, 2)
                wait_reloads(c, "certificate", "ok", 1)
                wait_reloads(c, "tokens", "ok", 1)
                # The open stream goes on over the connection made with the first certificate.
                for t in range(5, 10):
                    assert session.step([1.0, 0.0, 0.1 * t]).step == t
                # A new call with the dropped token is refused.
                with pytest.raises(Exception) as refused:
                    client.policies()
                assert "token" in str(refused.value).lower() or "unauthenticated" in str(refused.value).lower(), refused.value
                # New connections get the renewed certificate only.
                with Client(target, timeout=5, token=new_token, tls=TlsConfig(root_certificates=certs[1][0])) as renewed:
                    assert renewed.policies()
                with Client(target, timeout=5, token=new_token, tls=TlsConfig(root_certificates=certs[0][0])) as stale:
                    with pytest.raises(Exception):
                        stale.policies()
                # Garbage: the renewed certificate goes on serving, and the session stepping.
                kubelet_publish(secret, {"tls.crt": b"garbage", "tls.key": certs[1][1], "tokens": b""}, 3)
                wait_reloads(c, "certificate", "error", 1)
                wait_reloads(c, "tokens", "error", 1)
                with Client(target, timeout=5, token=new_token, tls=TlsConfig(root_certificates=certs[1][0])) as renewed:
                    assert renewed.policies()
                for t in range(10, 12):
                    assert session.step([1.0, 0.0, 0.1 * t]).step == t
    finally:
        shutil.rmtree(secret, ignore_errors=True)
    assert c.running()
    logs = c.logs()
    assert "TLS certificate reloaded" in logs and "TLS certificate not reloaded; serving the previous one" in logs, logs
