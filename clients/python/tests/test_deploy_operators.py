"""deploy/k8s for clusters with prometheus-operator and cert-manager (components/monitoring,
components/cert-manager, overlays/operators): the generated files match their sources, every
custom resource passes its operator's own schema (deploy/k8s/schema-check, which refuses a broken
one), the ServiceMonitor labels targets as the rules select them, and cert-manager writes the
Secret the Deployment mounts. Needs kubectl, node and deploy/k8s/schema-check's npm packages."""

from __future__ import annotations

import json
import pathlib
import re
import subprocess
import sys
from typing import Any

import pytest
import yaml

from conftest import REPO
from deploy_support import schema_check
from test_deploy_manifests import K8S, KUSTOMIZATIONS, built_in, find, render

PROMETHEUS = REPO / "deploy" / "prometheus"
MONITORING = K8S / "components" / "monitoring"
OPERATORS = K8S / "overlays" / "operators"


def validate(docs: list[dict[str, Any]]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(schema_check(), input=json.dumps(docs), capture_output=True, text=True)


def rules() -> list[dict[str, Any]]:
    groups: list[dict[str, Any]] = yaml.safe_load((PROMETHEUS / "rules" / "prac.rules.yml").read_text())["groups"]
    return groups


def test_the_generated_monitoring_files_are_what_scripts_monitoring_sync_writes() -> None:
    sync = subprocess.run([sys.executable, str(REPO / "scripts" / "monitoring-sync"), "--check"], capture_output=True, text=True)
    assert sync.returncode == 0, sync.stderr
    rule = yaml.safe_load((MONITORING / "prometheusrule.yaml").read_text())
    assert rule["spec"]["groups"] == rules()
    dashboard = yaml.safe_load((MONITORING / "grafana-dashboard.yaml").read_text())
    assert dashboard["data"] == {"prac-dashboard.json": (REPO / "deploy" / "grafana" / "prac-dashboard.json").read_text()}
    assert dashboard["metadata"]["labels"]["grafana_dashboard"] == "1"


@pytest.mark.parametrize("path", KUSTOMIZATIONS, ids=lambda p: p.name)
def test_every_overlays_custom_resources_pass_their_operators_schemas(path: pathlib.Path) -> None:
    docs = render(path)
    result = validate(docs)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.count("valid: ") == len([d for d in docs if not built_in(d)]), result.stdout
    print(f"{path.relative_to(REPO)}:\n{result.stdout}", end="")


def test_overlays_operators_has_the_custom_resources() -> None:
    custom = [d for d in render(OPERATORS) if not built_in(d)]
    assert sorted(d["kind"] for d in custom) == ["Certificate", "Certificate", "Issuer", "Issuer", "PrometheusRule", "ServiceMonitor"]
    assert validate(custom).stdout.count("valid: ") == len(custom)


def test_the_operator_schema_check_refuses_a_broken_object() -> None:
    docs = render(OPERATORS)
    certificate = find(docs, "Certificate", "prac-tls")
    certificate["spec"]["secretName"] = 5
    result = validate([certificate])
    assert result.returncode == 1
    assert "Certificate prac-tls: data/spec/secretName must be string" in result.stderr, result.stderr
    rule = find(docs, "PrometheusRule")
    rule["spec"]["groups"][1]["rules"][0]["for"] = "1 minute"
    assert "rules/0/for must match pattern" in validate([rule]).stderr
    # A custom resource it has no schema for fails instead of passing unchecked.
    unknown = {"apiVersion": "example.com/v1", "kind": "Thing", "metadata": {"name": "thing"}}
    result = validate([unknown])
    assert result.returncode == 1 and "no schema for this kind" in result.stderr


def test_the_service_monitor_scrapes_prac_metrics_with_the_label_the_rules_select() -> None:
    docs = render(OPERATORS)
    monitor = find(docs, "ServiceMonitor")["spec"]
    selected = [d for d in docs if d["kind"] == "Service" and monitor["selector"]["matchLabels"].items() <= d["metadata"]["labels"].items()]
    ports = [e["port"] for e in monitor["endpoints"]]
    scraped = [s["metadata"]["name"] for s in selected if any(p["name"] in ports for p in s["spec"]["ports"])]
    assert scraped == ["prac-metrics"]
    pod_labels = find(docs, "Deployment", "prac")["spec"]["template"]["metadata"]["labels"]
    [label] = monitor["podTargetLabels"]
    # prometheus-operator writes the pod's label under Prometheus's name for it.
    target_label = re.sub(r"[^a-zA-Z0-9_]", "_", label)
    selector = f'{target_label}="{pod_labels[label]}"'
    expressions = {r["alert"]: r["expr"] for g in rules() for r in g["rules"] if "alert" in r}
    assert selector in expressions["PracDown"]
    # Every rule reads `up` by that label or prac's own metrics, never a job's name.
    for group in rules():
        for rule in group["rules"]:
            assert not re.search(r"\bjob\s*!?[=~]", rule["expr"]), rule
            assert "up{" not in rule["expr"] or selector in rule["expr"], rule
    # deploy/prometheus/prometheus.yml gives its targets the same label.
    config = yaml.safe_load((PROMETHEUS / "prometheus.yml").read_text())
    jobs = {j["job_name"]: j for j in config["scrape_configs"]}
    relabel = [r for r in jobs["prac"]["relabel_configs"] if r.get("target_label") == target_label]
    assert relabel and relabel[0]["source_labels"] == [f"__meta_kubernetes_pod_label_{target_label}"]
    assert all(s["labels"][target_label] == pod_labels[label] for s in jobs["prac-static"]["static_configs"])


def hours(duration: str) -> float:
    found = re.fullmatch(r"(\d+)h", duration)
    assert found is not None, duration
    return float(found.group(1))


def test_cert_manager_writes_the_secret_the_deployment_mounts_from_a_ca_of_its_own() -> None:
    docs = render(OPERATORS)
    volumes = {v["name"]: v for v in find(docs, "Deployment", "prac")["spec"]["template"]["spec"]["volumes"]}
    secret = volumes["tls"]["secret"]["secretName"]
    served = [d for d in docs if d["kind"] == "Certificate" and d["spec"]["secretName"] == secret]
    assert len(served) == 1
    spec = served[0]["spec"]
    assert spec["privateKey"] == {"algorithm": "ECDSA", "size": 256, "rotationPolicy": "Always"}
    # Renewed well before PracCertificateExpiresSoon (14 days) would fire.
    assert 14 * 24 < hours(spec["renewBefore"]) < hours(spec["duration"])
    namespace = served[0]["metadata"]["namespace"]
    services = [s["metadata"]["name"] for s in yaml.safe_load_all((K8S / "base" / "service.yaml").read_text()) if s["metadata"]["name"] != "prac-metrics"]
    # The affinity proxy serves the same certificate under its own Service.
    proxy = find(render(K8S / "overlays" / "haproxy"), "Service", "prac-affinity")["metadata"]["name"]
    services.append(proxy)
    assert sorted(spec["dnsNames"]) == sorted(services + [f"{s}.{namespace}.svc" for s in services])
    # The chain: a CA Issuer whose CA certificate a self-signed Issuer signs, so prac-tls holds ca.crt.
    issuer = find(docs, "Issuer", spec["issuerRef"]["name"])
    ca = [d for d in docs if d["kind"] == "Certificate" and d["spec"]["secretName"] == issuer["spec"]["ca"]["secretName"]]
    assert len(ca) == 1 and ca[0]["spec"]["isCA"] is True
    assert find(docs, "Issuer", ca[0]["spec"]["issuerRef"]["name"])["spec"] == {"selfSigned": {}}
