"""deploy/prometheus and deploy/grafana against what they watch: the alert rules pass promtool's
check and their unit tests, each alert's runbook is a section of docs/operations.md, and every
metric the rules and the dashboard name exists on a running TLS server's /metrics. Needs promtool
for the first (Debian's prometheus package) and openssl for the last."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import time
import tomllib
import urllib.request
from typing import Iterator

import grpc
import pytest
import yaml

from conftest import REPO, prac_bin, self_signed
from deploy_support import tool
from prac_client import Client, ServerUnavailable, TlsConfig
from prac_client._proto.prac.v1 import prac_pb2 as pb
from prac_client._proto.prac.v1 import prac_pb2_grpc as pb_grpc

PROMETHEUS = REPO / "deploy" / "prometheus"
DASHBOARD = REPO / "deploy" / "grafana" / "prac-dashboard.json"


def test_the_alert_rules_pass_promtool_check_and_their_unit_tests() -> None:
    promtool = tool("promtool")
    check = subprocess.run([promtool, "check", "rules", "rules/prac.rules.yml"], cwd=PROMETHEUS, capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
    test = subprocess.run([promtool, "test", "rules", "tests/prac.rules.test.yml"], cwd=PROMETHEUS, capture_output=True, text=True)
    assert test.returncode == 0, test.stdout + test.stderr
    alerts = {r["alert"] for g in yaml.safe_load((PROMETHEUS / "rules" / "prac.rules.yml").read_text())["groups"] for r in g["rules"] if "alert" in r}
    tested = set(re.findall(r"alertname: (\w+)", (PROMETHEUS / "tests" / "prac.rules.test.yml").read_text()))
    assert alerts == tested, f"alerts without a unit test: {alerts - tested}"
    assert {"PracDown", "PracNotServing", "PracReplanLatencyHigh", "PracResourceExhausted", "PracSessionsNearLimit", "PracReloadFailed",
            "PracCertificateExpiresSoon", "PracCredentialReloadFailing"} <= alerts


@pytest.fixture
def metrics_text(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A TLS server (some metrics exist only with TLS) on the shipped bundles after a few steps,
    an error, a changed certificate and a reload: its /metrics."""
    tool("openssl")
    directory = tmp_path_factory.mktemp("tls")
    cert, key = self_signed(directory, days=30)
    process = subprocess.Popen(
        [prac_bin(), "serve", "--listen", "127.0.0.1:0", "--metrics-listen", "127.0.0.1:0", "--bundles", str(REPO / "bundles"),
         "--tls-cert", str(cert), "--tls-key", str(key)],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )
    try:
        assert process.stdout is not None
        lines = [process.stdout.readline() for _ in range(2)]
        metrics = next(l for l in lines if l.startswith("metrics on ")).removeprefix("metrics on ").strip()
        address = next(l for l in lines if l.startswith("listening on ")).removeprefix("listening on ").strip()
        # The certificate names localhost.
        target = "localhost:" + address.rpartition(":")[2]
        with Client(target, timeout=10, tls=TlsConfig(root_certificates=cert.read_bytes())) as client:
            deadline = time.monotonic() + 20
            while True:
                try:
                    if client.policies():
                        break
                except ServerUnavailable:
                    pass
                assert time.monotonic() < deadline
                time.sleep(0.05)
            with client.session("pendulum", epsilon_coef=0.01) as session:
                for t in range(10):
                    session.step([1.0, 0.0, 0.1 * t], new_episode=t == 0)
        with grpc.secure_channel(target, grpc.ssl_channel_credentials(cert.read_bytes())) as channel:
            with pytest.raises(grpc.RpcError):
                pb_grpc.PracStub(channel).GetPlan(pb.GetPlanRequest(session_id="no-such-session"), timeout=5)
        # A renewed certificate, as cert-manager writes one: the server re-reads it.
        new_cert, new_key = self_signed(tmp_path_factory.mktemp("renewed"), days=30)
        key.write_bytes(new_key.read_bytes())
        cert.write_bytes(new_cert.read_bytes())
        process.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 20
        while True:
            text = urllib.request.urlopen(f"http://{metrics}/metrics", timeout=5).read().decode()
            live = exposed(text)
            if {"prac_reloads_total", "prac_credential_reloads_total"} <= live:
                break
            if time.monotonic() > deadline:
                # The test names whatever else is missing.
                assert "prac_reloads_total" in live, text
                break
            time.sleep(0.1)
        yield text
    finally:
        process.terminate()
        process.wait(10)


def exposed(text: str) -> set[str]:
    return {line.split("{")[0].split(" ")[0] for line in text.splitlines() if line and not line.startswith("#")}


def named(expressions: list[str]) -> set[str]:
    # Not the recording rules' names (level:metric:operation), which are Prometheus's own.
    return {m for e in expressions for m in re.findall(r"(?<![:\w])prac_[a-z_]+(?![:\w])", e)}


def test_every_metric_the_dashboard_and_the_rules_name_is_on_a_live_server(metrics_text: str) -> None:
    live = exposed(metrics_text)
    dashboard = json.loads(DASHBOARD.read_text())
    expressions = [t["expr"] for p in dashboard["panels"] for t in p["targets"]]
    expressions += [v["query"] for v in dashboard["templating"]["list"] if v["type"] == "query"]
    rules = yaml.safe_load((PROMETHEUS / "rules" / "prac.rules.yml").read_text())
    rule_expressions = [r["expr"] for g in rules["groups"] for r in g["rules"]]
    adapter = yaml.safe_load((PROMETHEUS / "adapter-rules.yaml").read_text())
    adapter_expressions = [r["seriesQuery"] for r in adapter["rules"]]
    wanted = named(expressions + rule_expressions + adapter_expressions)
    missing = {m for m in wanted if m not in live}
    assert not missing, f"named but not exposed: {sorted(missing)}; exposed: {sorted(live)}"
    # The dashboard covers what the operators watch.
    for metric in ("prac_steps_total", "prac_step_latency_seconds_bucket", "prac_forecast_length_sum", "prac_f_t_sum",
                   "prac_plan_breaks_total", "prac_open_sessions", "prac_reloads_total"):
        assert metric in named(expressions), metric


# The runbooks live in the repository the image's source label names (Cargo.toml's repository).
RUNBOOKS = tomllib.loads((REPO / "Cargo.toml").read_text())["package"]["repository"] + "/blob/main/docs/operations.md#"


def anchors(markdown: str) -> dict[str, str]:
    """{anchor: heading} as GitHub makes them: lowercased, punctuation other than '-' and '_'
    dropped, spaces to '-', and a repeated anchor numbered (-1, -2, ...). Fenced code is skipped."""
    found: dict[str, str] = {}
    fenced = False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        heading = re.match(r"#{1,6} (.+)", line)
        if fenced or heading is None:
            continue
        slug = re.sub(r"[^\w\- ]", "", heading.group(1).strip().lower()).replace(" ", "-")
        anchor, n = slug, 0
        while anchor in found:
            n += 1
            anchor = f"{slug}-{n}"
        found[anchor] = heading.group(1).strip()
    return found


def test_every_alert_links_its_runbook_in_docs_operations() -> None:
    headings = anchors((REPO / "docs" / "operations.md").read_text())
    assert headings["alerts"] == "Alerts" and headings["hot-reload-sighup"] == "Hot reload (SIGHUP)"
    rules = yaml.safe_load((PROMETHEUS / "rules" / "prac.rules.yml").read_text())
    for rule in (r for g in rules["groups"] for r in g["rules"] if "alert" in r):
        url = rule["annotations"].get("runbook_url", "")
        assert url.startswith(RUNBOOKS), (rule["alert"], url)
        assert headings.get(url.removeprefix(RUNBOOKS)) == rule["alert"], (rule["alert"], url)
