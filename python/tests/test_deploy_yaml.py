"""Every YAML file under deploy/ parses, and says what it should: the KServe InferenceService runs `tether serve` on
8080 with v2 probes and the API key from a Secret; the Helm chart, rendered by helm_render.py (the Go-template
subset the chart uses, no helm binary needed), gives a Deployment with the /health and /live probes, the cache
volume, the Secret reference and the transports' ports as values ask. When `helm` is on PATH the chart is also
rendered by it and the two renderings compared."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path
from typing import Any, Dict, List

import pytest
import yaml

from helm_render import TemplateError, render_chart, render_string

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
CHART = DEPLOY / "helm" / "tether"

VARIANT = {
    "model": {"mode": "path", "path": "/models/smolvla-base-fp32", "name": "smolvla-base", "precision": "bf16"},
    "server": {"deadlineMs": 250, "extraArgs": ["--embodiment=so100", "--record=/var/lib/tether/cache/traces"]},
    "transports": {"openpiPort": 8001, "gr00tPort": 5555, "zmqPort": 5556},
    "apiKey": {"existingSecret": "fleet-key", "secretKey": "token"},
    "cache": {"type": "pvc", "size": "50Gi", "storageClass": "fast", "accessModes": ["ReadWriteMany"]},
    "resources": {"requests": {"cpu": "4", "memory": "8Gi"}},
    "nodeSelector": {"tether/accelerator": "cpu"},
    "podAnnotations": {"prometheus.io/scrape": "true"},
    "replicaCount": 3,
}


def docs(text: str) -> List[Dict[str, Any]]:
    return [d for d in yaml.safe_load_all(text) if d is not None]


def rendered(overrides: Dict[str, Any] = None) -> Dict[str, List[Dict[str, Any]]]:
    """kind -> documents of the rendered chart."""
    out: Dict[str, List[Dict[str, Any]]] = {}
    for name, text in render_chart(CHART, overrides).items():
        for d in docs(text):
            assert {"apiVersion", "kind", "metadata"} <= set(d), (name, d)
            out.setdefault(d["kind"], []).append(d)
    return out


def container(deployment: Dict[str, Any]) -> Dict[str, Any]:
    (c,) = deployment["spec"]["template"]["spec"]["containers"]
    return c


# -- the renderer itself, on cases whose Go-template output is known ------------------------------------------


@pytest.mark.parametrize("source, values, expected", [
    ("a\n  {{- if .Values.x }}\n  b: {{ .Values.x }}\n  {{- end }}\n", {"x": 1}, "a\n  b: 1\n"),
    ("a\n  {{- if .Values.x }}\n  b: {{ .Values.x }}\n  {{- end }}\n", {}, "a\n"),
    ("{{ if eq .Values.t \"pvc\" }}p{{ else if .Values.e }}e{{ else }}n{{ end }}", {"t": "x", "e": True}, "e"),
    ("{{ if and (eq .Values.t \"pvc\") (not .Values.c) }}yes{{ end }}", {"t": "pvc", "c": ""}, "yes"),
    ("{{ .Values.n | default \"d\" | quote }}", {}, '"d"'),
    ("{{ .Values.n | default \"d\" }}", {"n": "set"}, "set"),
    ("{{ printf \"%s-%s\" \"ab\" \"cd\" | trunc 3 | trimSuffix \"-\" }}", {}, "ab"),
    ("l:\n{{- range .Values.l }}\n- {{ . | quote }}\n{{- end }}", {"l": ["a", "b"]}, 'l:\n- "a"\n- "b"'),
    ("x:\n  {{- toYaml .Values.m | nindent 2 }}", {"m": {"b": 1, "a": 2}}, "x:\n  a: 2\n  b: 1"),
    ("{{/* a comment */}}v={{ .Values.v }}", {"v": 3}, "v=3"),
    ("{{ .Values.missing.deeper }}|", {}, "|"),
])
def test_renderer_semantics(source, values, expected):
    assert render_string(source, values) == expected


def test_renderer_include_and_unsupported():
    helpers = '{{- define "n" -}}{{ .Values.a }}-x{{- end -}}'
    assert render_string('{{ include "n" . | quote }}', {"a": "q"}, helpers) == '"q-x"'
    for bad in ('{{ lookup "v1" "Secret" "" "" }}', "{{ $x := 1 }}", "{{ if .Values.a }}unterminated"):
        with pytest.raises(TemplateError):
            render_string(bad, {"a": 1})


# -- plain YAML ---------------------------------------------------------------------------------------------------


def test_every_yaml_file_under_deploy_parses():
    files = [p for p in DEPLOY.rglob("*.y*ml") if "templates" not in p.parts]
    assert {p.relative_to(DEPLOY).as_posix() for p in files} >= {
        "kserve/inferenceservice.yaml", "helm/tether/Chart.yaml", "helm/tether/values.yaml"}
    for p in files:
        parsed = docs(p.read_text())
        assert parsed and all(isinstance(d, dict) for d in parsed), p


def test_inferenceservice_runs_tether_serve_with_the_v2_protocol():
    (isvc,) = docs((DEPLOY / "kserve" / "inferenceservice.yaml").read_text())
    assert isvc["apiVersion"] == "serving.kserve.io/v1beta1" and isvc["kind"] == "InferenceService"
    predictor = isvc["spec"]["predictor"]
    assert predictor["minReplicas"] >= 1 and predictor["maxReplicas"] >= predictor["minReplicas"]
    (c,) = predictor["containers"]
    assert c["name"] == "kserve-container"
    assert c["args"][:2] == ["serve", "/mnt/models"]
    assert "--port=8080" in c["args"] and "--host=0.0.0.0" in c["args"]
    assert any(a.startswith("--model-name=") for a in c["args"])
    assert c["ports"] == [{"name": "http1", "containerPort": 8080, "protocol": "TCP"}]
    assert c["readinessProbe"]["httpGet"] == {"path": "/v2/health/ready", "port": 8080}
    assert c["livenessProbe"]["httpGet"] == {"path": "/v2/health/live", "port": 8080}
    env = {e["name"]: e for e in c["env"]}
    assert env["TETHER_API_KEY"]["valueFrom"]["secretKeyRef"]["name"] == "tether-api-key"
    assert env["STORAGE_URI"]["value"]


# -- the Helm chart -----------------------------------------------------------------------------------------------


def test_chart_metadata():
    chart = yaml.safe_load((CHART / "Chart.yaml").read_text())
    assert chart["apiVersion"] == "v2" and chart["name"] == "tether" and chart["version"]


def test_chart_defaults():
    kinds = rendered()
    assert set(kinds) == {"Deployment", "Service"}  # no PVC (emptyDir) and no Secret (no key) by default
    (dep,) = kinds["Deployment"]
    (svc,) = kinds["Service"]
    assert dep["metadata"]["name"] == "robots-tether" == svc["metadata"]["name"]
    assert dep["spec"]["selector"]["matchLabels"] == svc["spec"]["selector"]
    assert dep["spec"]["template"]["metadata"]["labels"] == dep["spec"]["selector"]["matchLabels"]
    c = container(dep)
    assert c["image"] == "ghcr.io/example/tether:0.1.0"
    assert c["args"] == ["go", "--model=smolvla-demo", "--host=0.0.0.0", "--port=8000", "--max-batch=8",
                         "--batch-timeout-ms=0"]
    assert c["readinessProbe"]["httpGet"] == {"path": "/health", "port": "http"}
    assert c["livenessProbe"]["httpGet"] == {"path": "/live", "port": "http"}
    assert c["startupProbe"]["httpGet"]["path"] == "/live" and c["startupProbe"]["failureThreshold"] == 180
    assert [p["containerPort"] for p in c["ports"]] == [8000]
    env = {e["name"]: e for e in c["env"]}
    assert "TETHER_API_KEY" not in env
    assert env["TETHER_CACHE"]["value"] == "/var/lib/tether/cache"
    assert env["HF_HOME"]["value"] == "/var/lib/tether/cache/huggingface"
    assert c["volumeMounts"] == [{"name": "model-cache", "mountPath": "/var/lib/tether/cache"}]
    assert dep["spec"]["template"]["spec"]["volumes"] == [{"name": "model-cache", "emptyDir": {"sizeLimit": "20Gi"}}]
    assert "resources" not in c and "nodeSelector" not in dep["spec"]["template"]["spec"]
    assert svc["spec"]["ports"] == [{"name": "http", "port": 8000, "targetPort": "http", "protocol": "TCP"}]


def test_chart_with_every_option():
    kinds = rendered(VARIANT)
    assert set(kinds) == {"Deployment", "Service", "PersistentVolumeClaim"}  # existingSecret: no Secret made
    (dep,) = kinds["Deployment"]
    (pvc,) = kinds["PersistentVolumeClaim"]
    (svc,) = kinds["Service"]
    c = container(dep)
    assert dep["spec"]["replicas"] == 3
    assert c["args"][:2] == ["serve", "/models/smolvla-base-fp32"]
    for arg in ("--model-name=smolvla-base", "--precision=bf16", "--deadline-ms=250", "--openpi-port=8001",
                "--gr00t-port=5555", "--zmq-port=5556", "--embodiment=so100", "--record=/var/lib/tether/cache/traces"):
        assert arg in c["args"], arg
    env = {e["name"]: e for e in c["env"]}
    assert env["TETHER_API_KEY"]["valueFrom"]["secretKeyRef"] == {"name": "fleet-key", "key": "token"}
    assert {p["name"]: p["containerPort"] for p in c["ports"]} == {"http": 8000, "openpi": 8001, "gr00t": 5555,
                                                                   "zmq": 5556}
    assert {p["name"]: (p["port"], p["targetPort"]) for p in svc["spec"]["ports"]} == {
        "http": (8000, "http"), "openpi": (8001, "openpi"), "gr00t": (5555, "gr00t"), "zmq": (5556, "zmq")}
    volumes = dep["spec"]["template"]["spec"]["volumes"]
    assert volumes == [{"name": "model-cache", "persistentVolumeClaim": {"claimName": "robots-tether-cache"}}]
    assert pvc["metadata"]["name"] == "robots-tether-cache"
    assert pvc["spec"] == {"accessModes": ["ReadWriteMany"], "storageClassName": "fast",
                           "resources": {"requests": {"storage": "50Gi"}}}
    assert c["resources"] == {"requests": {"cpu": "4", "memory": "8Gi"}}
    assert dep["spec"]["template"]["spec"]["nodeSelector"] == {"tether/accelerator": "cpu"}
    assert dep["spec"]["template"]["metadata"]["annotations"] == {"prometheus.io/scrape": "true"}


def test_chart_secret_from_a_value_and_an_existing_claim():
    kinds = rendered({"apiKey": {"value": "s3cret"}, "cache": {"type": "pvc", "existingClaim": "shared-cache"}})
    assert "PersistentVolumeClaim" not in kinds
    (secret,) = kinds["Secret"]
    assert secret["metadata"]["name"] == "robots-tether-api-key"
    assert secret["stringData"] == {"api-key": "s3cret"}
    c = container(kinds["Deployment"][0])
    env = {e["name"]: e for e in c["env"]}
    assert env["TETHER_API_KEY"]["valueFrom"]["secretKeyRef"] == {"name": "robots-tether-api-key", "key": "api-key"}
    volumes = kinds["Deployment"][0]["spec"]["template"]["spec"]["volumes"]
    assert volumes[0]["persistentVolumeClaim"]["claimName"] == "shared-cache"


@pytest.mark.skipif(shutil.which("helm") is None, reason="helm is not installed (the default run renders without it)")
@pytest.mark.parametrize("overrides", [{}, VARIANT, {"apiKey": {"value": "s3cret"}}])
def test_helm_template_agrees(tmp_path, overrides):
    values = tmp_path / "values.yaml"
    values.write_text(yaml.safe_dump(overrides))
    out = subprocess.run(["helm", "template", "robots", str(CHART), "-f", str(values)], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    by_helm = sorted((d["kind"], d["metadata"]["name"], yaml.safe_dump(d)) for d in docs(out.stdout))
    ours = sorted((d["kind"], d["metadata"]["name"], yaml.safe_dump(d))
                  for ds in rendered(overrides).values() for d in ds)
    assert by_helm == ours
