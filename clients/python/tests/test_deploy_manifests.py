"""deploy/k8s as Kubernetes reads it: every overlay rendered by `kubectl kustomize` passes the
API's own schemas (kubernetes-validate, strict) for the oldest and newest Kubernetes it ships
(custom resources: test_deploy_operators.py), the pieces agree with each other and with the
image, and `podman kube play` of the rendered Deployment answers health. Needs kubectl (and
podman for the last test)."""

from __future__ import annotations

import pathlib
import re
import subprocess
import tomllib
import urllib.request
from typing import Any, Iterator

import kubernetes_validate
import kubernetes_validate.utils
import pytest
import yaml

from conftest import REPO
from deploy_support import SERVING, built_images, free_port, health, tool, wait_health

K8S = REPO / "deploy" / "k8s"
KUSTOMIZATIONS = [K8S / "base", *sorted(p for p in (K8S / "overlays").iterdir() if p.is_dir())]
VERSIONS = sorted(set(kubernetes_validate.utils.all_versions()), key=lambda v: tuple(int(x) for x in v.split(".")))
# The Kubernetes versions deploy/k8s supports (docs/deploy.md): 1.27, where gRPC probes are GA
# and matchLabelKeys is on by default, to the newest kubernetes-validate ships.
OLDEST, NEWEST = "1.27.0", VERSIONS[-1]
# Overlays that need a newer cluster: image volumes with subPath arrived in 1.33.
NEEDS = {"image-volume": "1.33.0"}


def version_key(version: str) -> tuple[int, ...]:
    return tuple(int(x) for x in version.split("."))


def render(path: pathlib.Path) -> list[dict[str, Any]]:
    out = subprocess.run([tool("kubectl"), "kustomize", str(path)], check=True, capture_output=True, text=True).stdout
    return [d for d in yaml.safe_load_all(out) if d]


def find(docs: list[dict[str, Any]], kind: str, name: str | None = None) -> dict[str, Any]:
    found = [d for d in docs if d["kind"] == kind and (name is None or d["metadata"]["name"] == name)]
    assert len(found) == 1, (kind, name, [d["metadata"]["name"] for d in docs if d["kind"] == kind])
    return found[0]


def server_container(docs: list[dict[str, Any]]) -> dict[str, Any]:
    container: dict[str, Any] = find(docs, "Deployment", "prac")["spec"]["template"]["spec"]["containers"][0]
    return container


def built_in(doc: dict[str, Any]) -> bool:
    """Of Kubernetes' own API groups: core ("v1"), dotless ones (apps, policy) and *.k8s.io.
    kubernetes-validate knows no others: test_deploy_operators.py checks those custom resources
    against their operators' schemas."""
    group = doc["apiVersion"].rpartition("/")[0]
    return "." not in group or group.endswith(".k8s.io")


@pytest.mark.parametrize("path", KUSTOMIZATIONS, ids=lambda p: p.name)
@pytest.mark.parametrize("version", [OLDEST, NEWEST])
def test_every_overlay_passes_the_kubernetes_schemas_strictly(path: pathlib.Path, version: str) -> None:
    assert OLDEST in VERSIONS
    version = max(version, NEEDS.get(path.name, OLDEST), key=version_key)
    docs = render(path)
    assert any(d["kind"] == "Deployment" for d in docs)
    own = [d for d in docs if built_in(d)]
    for doc in own:
        kubernetes_validate.validate(doc, version, strict=True)
    print(f"{path.relative_to(REPO)}: {len(own)} resources valid for Kubernetes {version}, {len(docs) - len(own)} custom")


def test_the_schema_check_refuses_an_unknown_field() -> None:
    docs = render(K8S / "base")
    deployment = find(docs, "Deployment", "prac")
    deployment["spec"]["template"]["spec"]["containers"][0]["readinesProbe"] = {"grpc": {"port": 8081}}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(deployment, NEWEST, strict=True)


def test_probes_ports_and_the_drain_agree_with_the_image_and_the_config() -> None:
    containerfile = (REPO / "deploy" / "container" / "Containerfile").read_text()
    docs = render(K8S / "base")
    container = server_container(docs)
    ports = {p["name"]: p["containerPort"] for p in container["ports"]}
    for flag, port in (("--listen", ports["grpc"]), ("--health-listen", ports["health"]), ("--metrics-listen", ports["metrics"])):
        assert re.search(rf'"{flag}", "0\.0\.0\.0:{port}"', containerfile), (flag, port)
    # The kubelet's gRPC probes reach the plaintext health port, never the TLS + token one.
    for probe in ("livenessProbe", "readinessProbe"):
        assert container[probe]["grpc"]["port"] == ports["health"], probe
    assert container["readinessProbe"]["grpc"]["service"] == "prac.v1.Prac"
    assert container["livenessProbe"]["grpc"]["service"] == "liveness"
    # Liveness answers at once and the init container has checked the bundles: a startup
    # probe would wait for nothing.
    assert "startupProbe" not in container
    config = tomllib.loads(find(docs, "ConfigMap")["data"]["prac.toml"])
    drain = int(config["drain_timeout"].removesuffix("s"))
    pause = container["lifecycle"]["preStop"]["exec"]["command"]
    assert pause[:2] == ["/usr/local/bin/prac", "sleep"]
    pod = find(docs, "Deployment", "prac")["spec"]["template"]["spec"]
    assert pod["terminationGracePeriodSeconds"] > int(pause[2].removesuffix("s")) + drain
    mounts = {m["mountPath"] for m in container["volumeMounts"]}
    for key in ("tls_cert", "tls_key", "auth_tokens"):
        assert any(config[key].startswith(m + "/") for m in mounts), (key, config[key], mounts)
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    assert pod["securityContext"]["runAsUser"] == 65532 and pod["securityContext"]["runAsNonRoot"] is True


def test_the_affinity_proxy_hashes_the_clients_header_over_the_headless_service() -> None:
    from prac_client import _channel

    docs = render(K8S / "overlays" / "envoy")
    configs = [d for d in docs if d["kind"] == "ConfigMap" and "envoy.yaml" in d["data"]]
    assert len(configs) == 1
    envoy = yaml.safe_load(configs[0]["data"]["envoy.yaml"])
    route = envoy["static_resources"]["listeners"][0]["filter_chains"][0]["filters"][0]["typed_config"]["route_config"]
    hashed = route["virtual_hosts"][0]["routes"][0]["route"]["hash_policy"][0]["header"]["header_name"]
    assert hashed == _channel.AFFINITY_HEADER
    cluster = envoy["static_resources"]["clusters"][0]
    assert cluster["lb_policy"] == "RING_HASH"
    address = cluster["load_assignment"]["endpoints"][0]["lb_endpoints"][0]["endpoint"]["address"]["socket_address"]
    headless = find(docs, "Service", "prac-headless")
    assert headless["spec"]["clusterIP"] == "None"
    assert (address["address"], address["port_value"]) == ("prac-headless", headless["spec"]["ports"][0]["port"])
    assert cluster["health_checks"][0]["grpc_health_check"]["service_name"] == "prac.v1.Prac"


def test_the_autoscaler_scales_on_the_metric_the_adapter_serves() -> None:
    docs = render(K8S / "overlays" / "hpa")
    hpa = find(docs, "HorizontalPodAutoscaler")
    assert "replicas" not in find(docs, "Deployment", "prac")["spec"]
    metric = hpa["spec"]["metrics"][0]["pods"]["metric"]["name"]
    adapter = yaml.safe_load((REPO / "deploy" / "prometheus" / "adapter-rules.yaml").read_text())
    assert metric in {rule["name"]["as"] for rule in adapter["rules"]}


@pytest.fixture
def played() -> Iterator[dict[str, int]]:
    podman = tool("podman")
    built_images()
    docs = render(K8S / "overlays" / "podman-test")
    keep = [d for d in docs if d["kind"] in ("Deployment", "ConfigMap")]
    ports = {}
    for p in server_container(keep)["ports"]:
        p["hostPort"] = ports[p["name"]] = free_port()
    path = pathlib.Path(f"/tmp/prac-kube-play-{free_port()}.yaml")
    path.write_text(yaml.safe_dump_all(keep))
    config_volume = find(keep, "ConfigMap")["metadata"]["name"]
    try:
        subprocess.run([podman, "kube", "play", str(path)], check=True, capture_output=True, text=True)
        yield ports
    finally:
        subprocess.run([podman, "kube", "down", str(path)], capture_output=True)
        subprocess.run([podman, "volume", "rm", "-f", config_volume], capture_output=True)
        path.unlink()


def test_podman_kube_play_of_the_rendered_deployment_answers_health(played: dict[str, int]) -> None:
    health_address = f"127.0.0.1:{played['health']}"
    wait_health(health_address, "prac.v1.Prac", SERVING)
    assert health(health_address, "liveness") == SERVING
    assert health(f"127.0.0.1:{played['grpc']}", "prac.v1.Prac") == SERVING
    metrics = urllib.request.urlopen(f"http://127.0.0.1:{played['metrics']}/metrics", timeout=5).read().decode()
    assert "prac_serving 1" in metrics


def bundles_volume(docs: list[dict[str, Any]]) -> dict[str, Any]:
    pod = find(docs, "Deployment", "prac")["spec"]["template"]["spec"]
    volume: dict[str, Any] = next(v for v in pod["volumes"] if v["name"] == "bundles")
    return volume


def test_bundles_arrive_from_an_image_by_default_and_no_claim_is_read_only_many() -> None:
    base = render(K8S / "base")
    pod = find(base, "Deployment", "prac")["spec"]["template"]["spec"]
    (init,) = pod["initContainers"]
    assert init["command"][1:] == ["copy-bundles", "/bundles", "/copy"]
    assert init["image"].endswith("-bundles")
    assert "emptyDir" in bundles_volume(base)
    assert not [d for d in base if d["kind"] == "PersistentVolumeClaim"]

    image = render(K8S / "overlays" / "image-volume")
    assert "initContainers" not in find(image, "Deployment", "prac")["spec"]["template"]["spec"]
    assert bundles_volume(image)["image"]["reference"] == init["image"]
    mount = next(m for m in server_container(image)["volumeMounts"] if m["name"] == "bundles")
    assert (mount["mountPath"], mount["subPath"]) == ("/bundles", "bundles")

    shared = render(K8S / "overlays" / "shared-volume")
    claim = find(shared, "PersistentVolumeClaim", "prac-bundles")
    assert claim["spec"]["accessModes"] == ["ReadWriteMany"]
    assert bundles_volume(shared)["persistentVolumeClaim"] == {"claimName": "prac-bundles", "readOnly": True}
    job = find(shared, "Job", "prac-bundles-writer")["spec"]["template"]["spec"]
    assert job["containers"][0]["command"] == init["command"]
    assert job["containers"][0]["image"] == init["image"]
    assert job["volumes"][0]["persistentVolumeClaim"]["claimName"] == "prac-bundles"

    for path in KUSTOMIZATIONS:
        for doc in render(path):
            if doc["kind"] == "PersistentVolumeClaim":
                assert "ReadOnlyMany" not in doc["spec"]["accessModes"], path


def test_the_network_policies_take_their_namespaces_from_one_place() -> None:
    network = yaml.safe_load((K8S / "base" / "network.yaml").read_text())["data"]
    for path in KUSTOMIZATIONS:
        docs = render(path)
        assert not [d for d in docs if d["metadata"]["name"] == "prac-network"], "build-time only"
        for policy in (d for d in docs if d["kind"] == "NetworkPolicy"):
            text = yaml.safe_dump(policy)
            assert "_NAMESPACE" not in text, (path, policy["metadata"]["name"])
    server = find(render(K8S / "base"), "NetworkPolicy", "prac")["spec"]["ingress"]
    by_port = {rule["ports"][0]["port"]: rule["from"][0]["namespaceSelector"]["matchLabels"] for rule in server}
    assert by_port["grpc"] == {"kubernetes.io/metadata.name": network["clientNamespace"]}
    assert by_port["metrics"] == {"kubernetes.io/metadata.name": network["monitoringNamespace"]}


def test_replicas_spread_per_rollout_and_the_guaranteed_overlay_gives_whole_cores() -> None:
    base = find(render(K8S / "base"), "Deployment", "prac")["spec"]["template"]["spec"]
    for spread in base["topologySpreadConstraints"]:
        assert spread["matchLabelKeys"] == ["pod-template-hash"]
    assert "cpu" not in base["containers"][0]["resources"]["limits"], "the base is not throttled"
    pod = find(render(K8S / "overlays" / "guaranteed"), "Deployment", "prac")["spec"]["template"]["spec"]
    # Guaranteed QoS: every container, init ones included, with requests equal to limits.
    for container in pod["containers"] + pod["initContainers"]:
        resources = container["resources"]
        assert resources["requests"] == resources["limits"], container["name"]
        assert str(resources["requests"]["cpu"]).isdigit(), "whole cores, for the static CPU manager"
