"""KServe / Open Inference Protocol v2 on the real `tether serve` binary, spoken to by the real Triton client
(`tritonclient.http.InferenceServerClient`): health, metadata, infer with binary and JSON tensor data, a batch of two
that shares a forward pass, the API key; raw HTTP for malformed requests; and the safety wedges, traces and metrics
of the "kserve" transport."""

from __future__ import annotations

import json
import struct
import subprocess
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import pytest

from pngutil import decode_png_rgb8
from serve_process import SAMPLE_PNG, ServeProcess, binary_path, metric, parse_metrics, request
from test_serve_integration import STATE, act_body, check_actions, ok_json, post_act

tritonclient_http = pytest.importorskip("tritonclient.http")
from tritonclient.utils import InferenceServerException  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

MODEL = "so-arm-demo"  # --model-name of the main server
DEFAULT_NAME = "smolvla-demo"  # the checkpoint directory's name
INSTRUCTION = "pick up the red cube"
CHUNK, DIM = 50, 6
SAMPLE = decode_png_rgb8(SAMPLE_PNG.read_bytes())  # H x W x 3 uint8: the pixels /act decodes from the PNG
INFER = f"/v2/models/{MODEL}/infer"


def client(server: ServeProcess) -> Any:
    return tritonclient_http.InferenceServerClient(f"127.0.0.1:{server.port}", network_timeout=120.0)


def inputs(states: List[List[float]], seeds: Optional[List[int]] = None, image: np.ndarray = SAMPLE,
           binary: bool = True, episode: Optional[str] = None) -> List[Any]:
    """The v2 input tensors of len(states) items, all with `image` and INSTRUCTION."""
    b = len(states)
    tensors = [
        ("instruction", np.array([INSTRUCTION.encode()] * b, dtype=np.object_), "BYTES"),
        ("state", np.asarray(states, dtype=np.float32), "FP32"),
        ("image.front", np.repeat(image[None], b, axis=0), "UINT8"),
    ]
    if seeds is not None:
        tensors.append(("seed", np.asarray(seeds, dtype=np.int64), "INT64"))
    if episode is not None:
        tensors.append(("episode_id", np.array([episode.encode()] * b, dtype=np.object_), "BYTES"))
    out = []
    for name, array, datatype in tensors:
        t = tritonclient_http.InferInput(name, list(array.shape), datatype)
        t.set_data_from_numpy(array, binary_data=binary)
        out.append(t)
    return out


def solo_act(server: ServeProcess, seed: int, state: List[float] = STATE, **headers: str) -> np.ndarray:
    """/act's answer for the same pixels (the sample PNG) and seed."""
    return check_actions(ok_json(post_act(server, act_body(seed=seed, state=state), headers)))


def v2_error(resp: Tuple[int, Dict[str, str], bytes], status: int, needle: str = "") -> str:
    """Checks the protocol's error form {"error": "<message>"} and returns the message."""
    got, headers, body = resp
    assert got == status, f"expected {status}, got {got}: {body[:500]!r}"
    assert headers.get("content-type", "").startswith("application/json"), headers
    err = json.loads(body)
    assert set(err) == {"error"} and isinstance(err["error"], str) and err["error"].strip(), err
    assert needle in err["error"], err["error"]
    return err["error"]


def tensor(name: str, datatype: str, shape: List[int], data: Any = None, size: Optional[int] = None) -> Dict:
    t: Dict[str, Any] = {"name": name, "datatype": datatype, "shape": shape}
    if data is not None:
        t["data"] = data
    if size is not None:
        t["parameters"] = {"binary_data_size": size}
    return t


def small_json_request(**replace: Any) -> Dict[str, Any]:
    """One item in JSON tensor data with a 2x2 image; `replace` swaps inputs by name (None removes one)."""
    tensors = {
        "instruction": tensor("instruction", "BYTES", [1], [INSTRUCTION]),
        "state": tensor("state", "FP32", [1, 6], STATE),
        "image.front": tensor("image.front", "UINT8", [1, 2, 2, 3], [128] * 12),
    }
    for name, t in replace.items():
        if t is None:
            tensors.pop(name)
        else:
            tensors[name] = t
    return {"inputs": list(tensors.values())}


def post_v2(server: ServeProcess, body: bytes, headers: Optional[Dict[str, str]] = None, path: str = INFER):
    return request(server.port, "POST", path, body, headers or {})


def metrics_of(server: ServeProcess) -> Dict:
    status, _, body = request(server.port, "GET", "/metrics")
    assert status == 200
    return parse_metrics(body.decode())


@pytest.fixture(scope="module")
def record_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("kserve-traces")


@pytest.fixture(scope="module")
def server(record_dir):
    # A batch window long enough that a request's items always share one forward pass.
    proc = ServeProcess(["--model-name", MODEL, "--batch-timeout-ms", "150", "--record", str(record_dir)])
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


KEY = "kserve-s3cret"


@pytest.fixture(scope="module")
def auth_server():
    proc = ServeProcess(["--max-body-bytes", "65536"], env={"TETHER_API_KEY": KEY})
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


# -- health and metadata through tritonclient ------------------------------------------------------------------


def test_health_and_server_metadata(server):
    c = client(server)
    assert c.is_server_live() and c.is_server_ready()
    assert c.is_model_ready(MODEL) and c.is_model_ready(MODEL, "1")
    assert not c.is_model_ready("no-such-model")
    meta = c.get_server_metadata()
    assert meta["name"] == "tether" and "binary_tensor_data" in meta["extensions"] and meta["version"]
    # The health answers are the status alone, as the protocol says.
    for path in ("/v2/health/live", "/v2/health/ready", f"/v2/models/{MODEL}/ready"):
        status, _, body = request(server.port, "GET", path)
        assert status == 200 and body == b"", (path, status, body)


def test_model_metadata(server):
    meta = client(server).get_model_metadata(MODEL)
    assert meta["name"] == MODEL and meta["versions"] == ["1"] and meta["platform"] == "tether_smolvla"
    ins = {t["name"]: t for t in meta["inputs"]}
    assert list(ins) == ["instruction", "state", "image.front", "seed", "episode_id"]
    assert ins["instruction"] == {"name": "instruction", "datatype": "BYTES", "shape": [-1]}
    assert ins["state"]["datatype"] == "FP32" and ins["state"]["shape"] == [-1, 6]
    assert ins["image.front"]["datatype"] == "UINT8" and ins["image.front"]["shape"] == [-1, -1, -1, 3]
    outs = {t["name"]: t for t in meta["outputs"]}
    assert outs["actions"] == {"name": "actions", "datatype": "FP32", "shape": [-1, CHUNK, DIM]}
    assert outs["action_source"]["datatype"] == "BYTES"
    assert client(server).get_model_metadata(MODEL, "1")["name"] == MODEL
    with pytest.raises(InferenceServerException) as e:
        client(server).get_model_metadata("other-model")
    assert e.value.status() == "404" and "unknown model 'other-model'" in e.value.message()


def test_health_while_warming_up():
    # Each forward pass (the warm-up's too) takes 3 s more: /v2/health/ready says false (400) meanwhile.
    proc = ServeProcess(["--inject-latency-ms", "3000"], wait_ready=False)
    try:
        assert request(proc.port, "GET", "/v2/health/live")[0] == 200
        assert request(proc.port, "GET", "/v2/health/ready")[0] == 400
        assert request(proc.port, "GET", f"/v2/models/{DEFAULT_NAME}/ready")[0] == 400
        status, headers, body = post_v2(proc, json.dumps(small_json_request()).encode(),
                                        path=f"/v2/models/{DEFAULT_NAME}/infer")
        v2_error((status, headers, body), 503, "not ready")
        assert headers["retry-after"] == "1"
        proc.wait_ready(60)
        assert client(proc).is_server_ready()
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- infer through tritonclient --------------------------------------------------------------------------------


def test_infer_binary_matches_act(server):
    expected = solo_act(server, seed=7)
    result = client(server).infer(MODEL, inputs([STATE], seeds=[7]), request_id="kserve-bin-1")
    # No outputs requested: tritonclient asks for every output in binary (binary_data_output).
    response = result.get_response()
    assert response["id"] == "kserve-bin-1" and response["model_name"] == MODEL
    assert all("binary_data_size" in o["parameters"] for o in response["outputs"])
    timing = response["parameters"]  # the server's time and the forward pass's, for the client to tell apart
    assert 0 < timing["tether_predict_ms"] <= timing["tether_total_ms"]
    actions = result.as_numpy("actions")
    assert actions.dtype == np.float32 and actions.shape == (1, CHUNK, DIM)
    np.testing.assert_array_equal(actions[0], expected)
    assert result.as_numpy("action_source").tolist() == [b"model"]


def test_infer_json_data_and_json_outputs(server):
    expected = solo_act(server, seed=9)
    outputs = [tritonclient_http.InferRequestedOutput("actions", binary_data=False)]
    result = client(server).infer(MODEL, inputs([STATE], seeds=[9], binary=False), outputs=outputs)
    response = result.get_response()
    assert [o["name"] for o in response["outputs"]] == ["actions"]
    assert "data" in response["outputs"][0] and "parameters" not in response["outputs"][0]
    np.testing.assert_array_equal(result.as_numpy("actions")[0], expected)
    assert result.as_numpy("action_source") is None  # not requested


def test_mixed_binary_and_json(server):
    expected = solo_act(server, seed=11)
    ins = inputs([STATE], seeds=[11])
    ins[0].set_data_from_numpy(np.array([INSTRUCTION.encode()], dtype=np.object_), binary_data=False)
    outputs = [tritonclient_http.InferRequestedOutput("action_source", binary_data=False),
               tritonclient_http.InferRequestedOutput("actions", binary_data=True)]
    result = client(server).infer(MODEL, ins, outputs=outputs)
    assert [o["name"] for o in result.get_response()["outputs"]] == ["action_source", "actions"]
    np.testing.assert_array_equal(result.as_numpy("actions")[0], expected)
    assert result.as_numpy("action_source").tolist() == ["model"]


def test_batch_of_two_shares_a_forward_pass(server):
    moved = [s + 5.0 for s in STATE]
    expected = [solo_act(server, seed=21), solo_act(server, seed=22, state=moved)]
    before = metrics_of(server)
    result = client(server).infer(MODEL, inputs([STATE, moved], seeds=[21, 22]))
    after = metrics_of(server)
    actions = result.as_numpy("actions")
    assert actions.shape == (2, CHUNK, DIM)
    np.testing.assert_array_equal(actions[0], expected[0])
    np.testing.assert_array_equal(actions[1], expected[1])
    # One forward pass of two: the items reached the batcher together.
    assert metric(after, "tether_batch_size_count") - metric(before, "tether_batch_size_count") == 1
    assert metric(after, "tether_batch_size_sum") - metric(before, "tether_batch_size_sum") == 2


def test_batch_with_nested_instruction_shape(server):
    """instruction as [B, 1], as some clients shape BYTES tensors."""
    ins = inputs([STATE, STATE], seeds=[3, 3])
    ins[0] = tritonclient_http.InferInput("instruction", [2, 1], "BYTES")
    ins[0].set_data_from_numpy(np.array([[INSTRUCTION.encode()], [INSTRUCTION.encode()]], dtype=np.object_))
    actions = client(server).infer(MODEL, ins).as_numpy("actions")
    np.testing.assert_array_equal(actions[0], actions[1])
    np.testing.assert_array_equal(actions[0], solo_act(server, seed=3))


def test_item_error_names_the_item(server):
    ins = inputs([STATE, [float("nan")] * 6], seeds=[1, 2])
    with pytest.raises(InferenceServerException) as e:
        client(server).infer(MODEL, ins)
    assert e.value.status() == "400" and "item 1" in e.value.message() and "state" in e.value.message()


def test_auth_through_headers(auth_server):
    c = client(auth_server)
    small = np.full((8, 8, 3), 90, dtype=np.uint8)
    assert c.is_server_live() and c.is_server_ready() and c.is_model_ready(DEFAULT_NAME)  # health stays open
    with pytest.raises(InferenceServerException) as e:
        c.infer(DEFAULT_NAME, inputs([STATE], image=small))
    assert e.value.status() == "401" and "API key is required" in e.value.message()
    with pytest.raises(InferenceServerException) as e:
        c.infer(DEFAULT_NAME, inputs([STATE], image=small), headers={"Authorization": "Bearer wrong"})
    assert e.value.status() == "401" and "not valid" in e.value.message()
    with pytest.raises(InferenceServerException) as e:
        c.get_model_metadata(DEFAULT_NAME)
    assert e.value.status() == "401"
    for headers in ({"Authorization": f"Bearer {KEY}"}, {"X-Tether-Key": KEY}):
        assert c.get_model_metadata(DEFAULT_NAME, headers=headers)["name"] == DEFAULT_NAME
        actions = c.infer(DEFAULT_NAME, inputs([STATE], image=small, seeds=[1]), headers=headers).as_numpy("actions")
        assert actions.shape == (1, CHUNK, DIM) and np.all(np.isfinite(actions))


# -- raw HTTP: malformed requests ------------------------------------------------------------------------------


def test_malformed_json(server):
    v2_error(post_v2(server, b'{"inputs": [', {"Content-Type": "application/json"}), 400, "not valid JSON")
    v2_error(post_v2(server, b"[1, 2]"), 400, "JSON object")
    v2_error(post_v2(server, b'{"inputs": []}'), 400, "'inputs'")


@pytest.mark.parametrize("replace, needle", [
    ({"state": tensor("state", "FP64", [1, 6], STATE)}, "input 'state': datatype 'FP64'"),
    ({"image.front": tensor("image.front", "FP32", [1, 2, 2, 3], [0.5] * 12)}, "input 'image.front': datatype 'FP32'"),
    ({"state": tensor("state", "FP32", [1, 5], STATE[:5])}, "input 'state': shape [1, 5]"),
    ({"image.front": tensor("image.front", "UINT8", [1, 2, 2, 4], [1] * 16)}, "input 'image.front': shape [1, 2, 2, 4]"),
    ({"image.front": tensor("image.front", "UINT8", [1, 2, 2, 3], [1] * 11)}, "'data' has 11 elements"),
    ({"state": tensor("state", "FP32", [2, 6], STATE * 2)}, "batch size 2"),
    ({"gripper": tensor("gripper", "FP32", [1], [1.0])}, "unknown input tensor 'gripper'"),
    ({"image.top": tensor("image.top", "UINT8", [1, 2, 2, 3], [1] * 12)}, "input 'image.top'"),
    ({"state": None}, "'state'"),
    ({"image.front": None}, "image input is required"),
    ({"seed": tensor("seed", "INT64", [1], [-3])}, "input 'seed'"),
])
def test_wrong_tensors_are_400_naming_the_tensor(server, replace, needle):
    v2_error(post_v2(server, json.dumps(small_json_request(**replace)).encode()), 400, needle)


def test_truncated_binary_data(server):
    state = struct.pack("<6f", *STATE)
    body = small_json_request(state=tensor("state", "FP32", [1, 6], size=len(state)))
    header = json.dumps(body).encode()
    full = {"Inference-Header-Content-Length": str(len(header))}
    assert post_v2(server, header + state, full)[0] == 200
    v2_error(post_v2(server, header + state[:-4], full), 400, "binary_data_size 24, but only 20 bytes")
    v2_error(post_v2(server, header + state + b"xyz", full), 400, "3 bytes of binary data follow")
    v2_error(post_v2(server, header + state), 400, "no Inference-Header-Content-Length")
    v2_error(post_v2(server, header + state, {"Inference-Header-Content-Length": str(len(header) + 100)}), 400,
             "exceeds the body")
    # BYTES: an element whose 4-byte length runs past the data.
    instr = struct.pack("<I", 50) + b"short"
    body = small_json_request(instruction=tensor("instruction", "BYTES", [1], size=len(instr)))
    header = json.dumps(body).encode()
    v2_error(post_v2(server, header + instr, {"Inference-Header-Content-Length": str(len(header))}), 400,
             "element 0 declares 50 bytes")


def test_unknown_model_version_path_and_method(server):
    body = json.dumps(small_json_request()).encode()
    v2_error(post_v2(server, body, path="/v2/models/nope/infer"), 404, "unknown model 'nope'")
    v2_error(post_v2(server, body, path=f"/v2/models/{MODEL}/versions/7/infer"), 404, "no version '7'")
    assert post_v2(server, body, path=f"/v2/models/{MODEL}/versions/1/infer")[0] == 200
    v2_error(request(server.port, "GET", INFER), 405, "POST")
    v2_error(request(server.port, "POST", "/v2/health/ready", b""), 405, "GET")
    v2_error(request(server.port, "GET", "/v2/models"), 404, "no endpoint")
    v2_error(post_v2(server, body, {"Content-Encoding": "gzip"}), 400, "Content-Encoding")


def test_unknown_output_is_refused(server):
    req = small_json_request()
    req["outputs"] = [{"name": "logits"}]
    v2_error(post_v2(server, json.dumps(req).encode()), 400, "unknown output tensor 'logits'")


def test_wrong_key_and_body_limit_raw(auth_server):
    body = json.dumps(small_json_request()).encode()
    path = f"/v2/models/{DEFAULT_NAME}/infer"
    v2_error(post_v2(auth_server, body, path=path), 401, "API key is required")
    v2_error(post_v2(auth_server, body, {"X-Tether-Key": "nope"}, path=path), 401, "not valid")
    assert post_v2(auth_server, body, {"X-Tether-Key": KEY}, path=path)[0] == 200
    # --max-body-bytes 65536: refused while reading, in the protocol's form.
    big = json.dumps(small_json_request(**{"image.front": tensor("image.front", "UINT8", [1, 100, 100, 3],
                                                                 [7] * 30000)})).encode()
    v2_error(post_v2(auth_server, big, {"X-Tether-Key": KEY}, path=path), 413, "--max-body-bytes")


# -- wedges, traces and metrics on the kserve transport --------------------------------------------------------


def test_guard_clamps_kserve_answers(tmp_path, server):
    raw = client(server).infer(MODEL, inputs([STATE], seeds=[5])).as_numpy("actions")[0]
    safety = tmp_path / "limits.json"
    safety.write_text(json.dumps({"joint_limits": {"shoulder_pan": {"has_position_limits": True,
                                                                    "min_position": -5.0, "max_position": 5.0}}}))
    proc = ServeProcess(["--embodiment", "so100", "--safety-config", str(safety),
                         "--audit-log", str(tmp_path / "audit.jsonl")])
    try:
        actions = client(proc).infer(DEFAULT_NAME, inputs([STATE], seeds=[5])).as_numpy("actions")[0]
        assert np.all(np.abs(actions[:, 0]) <= 5.0)
        assert np.any(np.abs(raw[:, 0]) > 5.0), "the limit must bite for this test to mean anything"
        # so100's velocity limits hold too: consecutive rows move at most max_velocity / control rate.
        assert np.all(np.abs(np.diff(actions[:, :5], axis=0)) <= 150 / 30 + 1e-3)
        assert metric(metrics_of(proc), "tether_guard_clamped_total") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_deadline_answers_from_the_last_good_chunk():
    proc = ServeProcess(["--inject-latency-ms", "600", "--deadline-ms", "150", "--request-timeout-ms", "5000",
                         "--control-rate-hz", "10"])
    try:
        c = client(proc)
        with pytest.raises(InferenceServerException) as e:
            c.infer(DEFAULT_NAME, inputs([STATE], seeds=[7], episode="slow"))
        assert e.value.status() == "504" and "--deadline-ms" in e.value.message()
        # The late forward pass becomes the episode's last good chunk (as on /act: test_wedges.py).
        for _ in range(120):
            try:
                result = c.infer(DEFAULT_NAME, inputs([STATE], seeds=[7], episode="slow"))
                break
            except InferenceServerException as err:
                assert err.status() == "504", err
                time.sleep(0.5)
        else:
            raise AssertionError("the late forward pass never became the last good chunk")
        assert result.as_numpy("action_source").tolist() == [b"last_good"]
        assert np.all(np.isfinite(result.as_numpy("actions")))
        assert metric(metrics_of(proc), "tether_deadline_exceeded_total") >= 2
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_breaker_opens_on_kserve_failures(tmp_path):
    fault = tmp_path / "fail-now"
    proc = ServeProcess(["--max-consecutive-crashes", "2", "--inject-failure-file", str(fault)])
    try:
        fault.touch()
        body = json.dumps(small_json_request()).encode()
        path = f"/v2/models/{DEFAULT_NAME}/infer"
        for _ in range(2):
            v2_error(post_v2(proc, body, path=path), 500, "injected failure")
        status, headers, data = post_v2(proc, body, path=path)
        v2_error((status, headers, data), 503, "circuit is open")
        assert headers["retry-after"] == "60"
        assert not client(proc).is_server_ready()  # /v2/health/ready follows /health
        m = metrics_of(proc)
        assert metric(m, "tether_circuit_open") == 1 and metric(m, "tether_circuit_rejected_total") == 1
        assert metric(m, "tether_requests_total", transport="kserve", status="500") == 2
        assert metric(m, "tether_requests_total", transport="kserve", status="503") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_traces_record_the_transport(server, record_dir):
    headers = {"X-Tether-Request-ID": "kserve-trace-1"}
    client(server).infer(MODEL, inputs([STATE, STATE], seeds=[1, 2], episode="trace-ep"), headers=headers)
    v2_error(post_v2(server, json.dumps(small_json_request(state=tensor("state", "FP32", [1, 6], [1e39] * 6))).encode(),
                     {"X-Tether-Request-ID": "kserve-trace-bad"}), 400, "state")
    deadline = time.monotonic() + 10
    while True:
        lines = [json.loads(l) for f in sorted(record_dir.glob("trace-*.jsonl")) for l in f.read_text().splitlines()]
        mine = {l["request_id"]: l for l in lines if l["request_id"].startswith("kserve-trace-1")}
        if len(mine) == 2 or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    # A batch's items each leave a line, under "<request id>.<item>".
    assert set(mine) == {"kserve-trace-1.0", "kserve-trace-1.1"}, sorted(mine)
    for line in mine.values():
        assert line["transport"] == "kserve" and line["status"] == "success"
        assert line["episode_id"] == "trace-ep" and line["task"] == INSTRUCTION and line["model"] == DEFAULT_NAME
    assert [mine[k]["inputs"]["seed"] for k in sorted(mine)] == [1, 2]
    assert all(l["transport"] == "kserve" for l in lines if l["request_id"].startswith("kserve-"))
    # /act requests on the same server are traced as http.
    assert any(l["transport"] == "http" for l in lines)


def test_requests_refused_while_decoding_are_traced(server, record_dir):
    v2_error(post_v2(server, b"{oops", {"X-Tether-Request-ID": "kserve-undecodable"}), 400, "JSON")
    deadline = time.monotonic() + 10
    while True:
        lines = [json.loads(l) for f in sorted(record_dir.glob("trace-*.jsonl")) for l in f.read_text().splitlines()]
        mine = [l for l in lines if l["request_id"] == "kserve-undecodable"]
        if mine or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert len(mine) == 1, [l["request_id"] for l in lines]
    assert mine[0]["transport"] == "kserve" and mine[0]["status"] == "failed" and mine[0]["http_status"] == 400
    assert mine[0]["error"]["code"] == "bad_json"
    # The line extends the hash chain: every earlier line is intact.
    verify = subprocess.run([str(binary_path()), "traces", "verify", "--dir", str(record_dir)], capture_output=True,
                            text=True, timeout=60)
    assert verify.returncode == 0, verify.stdout + verify.stderr


def test_metrics_count_by_transport(server):
    before = metrics_of(server)
    client(server).infer(MODEL, inputs([STATE], seeds=[1]))
    client(server).is_server_ready()
    client(server).get_model_metadata(MODEL)
    post_v2(server, b"{oops")
    post_act(server, act_body())
    after = metrics_of(server)

    def delta(**labels: str) -> float:
        return metric(after, "tether_requests_total", **labels) - metric(before, "tether_requests_total", **labels)

    assert delta(transport="kserve", endpoint="/v2/models/{name}/infer", status="200") == 1
    assert delta(transport="kserve", endpoint="/v2/models/{name}/infer", status="400") == 1
    assert delta(transport="kserve", endpoint="/v2/health/ready", status="200") == 1
    assert delta(transport="kserve", endpoint="/v2/models/{name}", status="200") == 1
    assert delta(transport="http", endpoint="/act", status="200") == 1
    assert delta(transport="kserve", endpoint="/act") == 0 and delta(transport="http", endpoint="other") == 0
