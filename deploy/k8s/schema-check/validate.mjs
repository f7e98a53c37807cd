// Validates rendered manifests against prometheus-operator's and cert-manager's own CRD schemas
// (the @kubernetes-models packages, pinned in package.json), which kubernetes-validate lacks:
//   kubectl kustomize deploy/k8s/overlays/operators | node deploy/k8s/schema-check/validate.mjs
// Reads YAML (or JSON) documents from the files named, or stdin; a document may also be an array
// of objects, or a List with items. Objects of built-in API groups pass through unchecked; one of
// any other group without a schema here fails, so that no custom resource goes unchecked.
// Prints `valid: ...` per object checked; exits 1 with `invalid: ...` per object refused.
import { readFileSync } from "node:fs";
import { parseAllDocuments } from "yaml";
import { PodMonitor } from "@kubernetes-models/prometheus-operator/monitoring.coreos.com/v1/PodMonitor";
import { PrometheusRule } from "@kubernetes-models/prometheus-operator/monitoring.coreos.com/v1/PrometheusRule";
import { ServiceMonitor } from "@kubernetes-models/prometheus-operator/monitoring.coreos.com/v1/ServiceMonitor";
import { Certificate } from "@kubernetes-models/cert-manager/cert-manager.io/v1/Certificate";
import { ClusterIssuer } from "@kubernetes-models/cert-manager/cert-manager.io/v1/ClusterIssuer";
import { Issuer } from "@kubernetes-models/cert-manager/cert-manager.io/v1/Issuer";

const MODELS = new Map(
  [PodMonitor, PrometheusRule, ServiceMonitor, Certificate, ClusterIssuer, Issuer].map((m) => [`${m.apiVersion}/${m.kind}`, m]),
);

// Kubernetes' own groups: the core group ("v1"), dotless ones (apps, policy) and *.k8s.io.
function builtIn(apiVersion) {
  const group = apiVersion.includes("/") ? apiVersion.split("/")[0] : "";
  return !group.includes(".") || group.endsWith(".k8s.io");
}

const valid = [];
const invalid = [];

function check(object) {
  if (object === null || object === undefined) return;
  if (typeof object !== "object" || Array.isArray(object)) {
    invalid.push(`not an object: ${JSON.stringify(object).slice(0, 80)}`);
    return;
  }
  const apiVersion = String(object.apiVersion ?? "");
  const what = `${apiVersion} ${object.kind} ${object.metadata?.name ?? "(no name)"}`;
  const Model = MODELS.get(`${apiVersion}/${object.kind}`);
  if (Model === undefined) {
    if (!builtIn(apiVersion)) invalid.push(`${what}: no schema for this kind here (validate.mjs's MODELS)`);
    return;
  }
  try {
    new Model(object).validate();
    valid.push(what);
  } catch (error) {
    invalid.push(`${what}: ${error.message}`);
  }
}

for (const input of process.argv.length > 2 ? process.argv.slice(2) : ["/dev/stdin"]) {
  for (const doc of parseAllDocuments(readFileSync(input, "utf8"))) {
    if (doc.errors.length > 0) {
      invalid.push(`${input}: not YAML: ${doc.errors[0].message}`);
      continue;
    }
    const found = doc.toJS();
    const objects = Array.isArray(found) ? found : found?.kind?.endsWith("List") ? (found.items ?? []) : [found];
    objects.forEach(check);
  }
}
for (const line of valid) console.log(`valid: ${line}`);
for (const line of invalid) console.error(`invalid: ${line}`);
process.exit(invalid.length > 0 ? 1 : 0);
