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


def haproxy_sections(config: str) -> dict[str, list[str]]:
    """haproxy.cfg's sections ("global", "backend prac", ...) and their lines, comments dropped."""
    sections: dict[str, list[str]] = {}
    current: list[str] = []
    for line in config.splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        if not line[0].isspace():
            current = sections.setdefault(line.strip(), [])
        else:
            current.append(line.strip())
    return sections


def test_the_affinity_proxy_hashes_the_clients_header_over_the_headless_service() -> None:
    from prac_client import _channel

    docs = render(K8S / "overlays" / "haproxy")
    configs = [d for d in docs if d["kind"] == "ConfigMap" and "haproxy.cfg" in d["data"]]
    assert len(configs) == 1
    config = configs[0]["data"]["haproxy.cfg"]
    assert config == (REPO / "deploy" / "haproxy" / "haproxy.cfg").read_text()
    sections = haproxy_sections(config)
    backend = sections["backend prac"]
    # Each call hashed on the client's header, consistently: a lost replica moves only its share.
    assert f"balance hdr({_channel.AFFINITY_HEADER})" in backend
    assert "hash-type consistent" in backend
    # Readiness from prac's /readyz on the metrics port; a replica marked down ends its streams.
    headless = find(docs, "Service", "prac-headless")
    metrics_port = {p["name"]: p["containerPort"] for p in server_container(docs)["ports"]}["metrics"]
    assert "option httpchk" in backend and "http-check expect status 200" in backend
    assert any(re.fullmatch(r"http-check send meth GET uri /readyz\b.*", line) for line in backend), backend
    defaults = next(line.split() for line in backend if line.startswith("default-server "))
    assert defaults[defaults.index("port") + 1] == str(metrics_port)
    assert defaults[defaults.index("on-marked-down") + 1] == "shutdown-sessions"
    assert defaults[defaults.index("verify") + 1] == "required"
    assert defaults[defaults.index("alpn") + 1] == "h2"
    # The replicas from the headless Service's DNS, on its gRPC port, and the resolvers it names.
    template = next(line for line in backend if line.startswith("server-template "))
    host = f"prac-headless.${{POD_NAMESPACE}}.svc.${{CLUSTER_DOMAIN}}:{headless['spec']['ports'][0]['port']}"
    assert template.split()[3] == f'"{host}"', template
    assert headless["spec"]["clusterIP"] == "None"
    resolvers = defaults[defaults.index("resolvers") + 1]
    assert f"resolvers {resolvers}" in sections
    # TLS in, with ALPN h2, from the Secret the proxy mounts.
    bind = next(line.split() for line in sections["frontend grpc"] if line.startswith("bind "))
    assert bind[bind.index("alpn") + 1] == "h2"
    proxy = find(docs, "Deployment", "prac-affinity")["spec"]["template"]["spec"]
    container = proxy["containers"][0]
    mounts = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
    volumes = {v["name"]: v for v in proxy["volumes"]}
    assert volumes["tls"]["secret"]["secretName"] == "prac-tls"
    assert bind[bind.index("crt") + 1] == f"{mounts['tls']}/tls.crt"
    assert defaults[defaults.index("ca-file") + 1] == f"{mounts['tls']}/ca.crt"
    assert volumes["config"]["configMap"]["name"] == configs[0]["metadata"]["name"]
    assert mounts["config"] == "/etc/haproxy"
    env = {e["name"]: e for e in container["env"]}
    assert env["POD_NAMESPACE"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.namespace"
    # The probes reach what HAProxy serves on its probe port.
    probes = {p["name"]: p["containerPort"] for p in container["ports"]}
    assert any(line == f"bind :{probes['probes']}" for line in sections["frontend probes"])
    for probe, path in (("readinessProbe", "/readyz"), ("livenessProbe", "/livez")):
        assert container[probe]["httpGet"] == {"path": path, "port": "probes"}
        assert any(f"{{ path {path} }}" in line for line in sections["frontend probes"]), path
    # The drain (grace + hard-stop-after) fits the termination grace period.
    seconds = {line.split()[0]: int(line.split()[1].removesuffix("s")) for line in sections["global"]
               if line.split()[0] in ("grace", "hard-stop-after", "close-spread-time")}
    assert seconds["close-spread-time"] < seconds["hard-stop-after"]
    assert proxy["terminationGracePeriodSeconds"] > seconds["grace"] + seconds["hard-stop-after"]
    containerfile = (REPO / "deploy" / "haproxy" / "Containerfile").read_text()
    assert "\nSTOPSIGNAL SIGUSR1\n" in containerfile
    assert container["securityContext"]["readOnlyRootFilesystem"] is True
    assert proxy["securityContext"]["runAsUser"] == 65532 and proxy["securityContext"]["runAsNonRoot"] is True
    # The replicas take gRPC from the proxy alone, and its /readyz checks on their metrics port.
    policy = find(docs, "NetworkPolicy", "prac")
    proxy_labels = find(docs, "Deployment", "prac-affinity")["spec"]["template"]["metadata"]["labels"]

    def from_proxy(peer: dict[str, Any]) -> bool:
        labels = peer.get("podSelector", {}).get("matchLabels", {})
        return bool(labels) and "namespaceSelector" not in peer and labels.items() <= proxy_labels.items()

    admitted: dict[str, list[dict[str, Any]]] = {}
    for rule in policy["spec"]["ingress"]:
        for port in rule["ports"]:
            # A rule without `from` admits anyone.
            admitted.setdefault(port["port"], []).extend(rule.get("from", [{}]))
    assert admitted["grpc"] and all(from_proxy(peer) for peer in admitted["grpc"]), admitted["grpc"]
    assert any(from_proxy(peer) for peer in admitted["metrics"]), admitted["metrics"]
    own = find(docs, "NetworkPolicy", "prac-affinity")
    egress_ports = {p["port"] for rule in own["spec"]["egress"] for p in rule["ports"]}
    assert {"grpc", "metrics", 53} <= egress_ports
    # Its clients and Prometheus come from the namespaces base/network.yaml sets for the replicas.
    network = yaml.safe_load((K8S / "base" / "network.yaml").read_text())["data"]
    namespaces = {p["port"]: rule["from"][0]["namespaceSelector"]["matchLabels"]["kubernetes.io/metadata.name"]
                  for rule in own["spec"]["ingress"] for p in rule["ports"]}
    assert namespaces == {"grpc": network["clientNamespace"], "probes": network["monitoringNamespace"]}


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
