"""The real `tether serve` binary over real HTTP: every endpoint and error code of the API contract, auth, limits,
request ids, metrics, a bounded load burst, graceful SIGTERM and the client's retries while the model warms up."""

from __future__ import annotations

import base64
import concurrent.futures
import hashlib
import json
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import pytest

from pngutil import decode_png_rgb8, encode_png
from serve_process import (
    DEMO,
    FIXTURE_IMAGES,
    SAMPLE_PNG,
    ServeProcess,
    binary_path,
    metric,
    parse_metrics,
    parse_raw_response,
    raw_exchange,
    request,
)
from tether_client import (
    AuthenticationError,
    InvalidRequestError,
    RequestTimeoutError,
    TetherClient,
)

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(
        not binary_path().is_file(),
        reason=f"tether binary not found at {binary_path()} (build it, or set TETHER_BINARY)",
    ),
]

STATE = [0.0, 90.0, 90.0, 45.0, 0.0, 20.0]
INSTRUCTION = "pick up the red cube"
SAMPLE_BYTES = SAMPLE_PNG.read_bytes()
SAMPLE_B64 = base64.b64encode(SAMPLE_BYTES).decode()
JPEG_PATH = FIXTURE_IMAGES / "images" / "camera_240x320.jpg"
CAMERA = "observation.images.front"
REQUEST_ID_RE = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")
ERROR_CODES = {
    400: {"bad_json", "bad_msgpack", "invalid_field", "invalid_state", "invalid_image", "unknown_camera",
          "unknown_field", "missing_field"},
    401: {"unauthorized"},
    404: {"not_found"},
    405: {"method_not_allowed"},
    413: {"body_too_large"},
    431: {"header_too_large"},
}
_UNSET = object()


def act_body(**fields: Any) -> bytes:
    """A valid /act body with ``fields`` replaced (a field set to _UNSET is removed)."""
    body: Dict[str, Any] = {"instruction": INSTRUCTION, "state": STATE, "image": SAMPLE_B64, "seed": 7}
    body.update(fields)
    return json.dumps({k: v for k, v in body.items() if v is not _UNSET}).encode()


def post_act(server: ServeProcess, body: bytes, headers: Optional[Dict[str, str]] = None):
    h = {"Content-Type": "application/json"}
    h.update(headers or {})
    return request(server.port, "POST", "/act", body, h)


def ok_json(resp: Tuple[int, Dict[str, str], bytes]) -> Dict[str, Any]:
    status, headers, body = resp
    assert status == 200, f"expected 200, got {status}: {body[:500]!r}"
    assert headers.get("content-type", "").startswith("application/json")
    return json.loads(body)


def check_actions(data: Dict[str, Any]) -> np.ndarray:
    actions = np.asarray(data["actions"], dtype=np.float32)
    assert actions.shape == (50, 6) and data["num_actions"] == 50 and data["action_dim"] == 6
    assert np.all(np.isfinite(actions))
    return actions


def expect_error(resp: Tuple[int, Dict[str, str], bytes], status: int, code: Optional[str] = None) -> Dict[str, Any]:
    """Checks the error shape of the contract and returns the error object."""
    got_status, headers, body = resp
    assert got_status == status, f"expected {status} {code}, got {got_status}: {body[:500]!r}"
    assert headers.get("content-type", "").startswith("application/json"), headers
    assert REQUEST_ID_RE.match(headers.get("x-tether-request-id", "")), headers
    err = json.loads(body)["error"]
    assert isinstance(err["message"], str) and err["message"].strip(), err
    if code is not None:
        assert err["code"] == code, f"expected code {code}, got {err}"
    assert err["code"] in ERROR_CODES.get(status, {err["code"]}), err
    return err


def _b64_file(rel: str) -> str:
    return base64.b64encode((FIXTURE_IMAGES / rel).read_bytes()).decode()


def model_hash() -> str:
    return "sha256:" + hashlib.sha256((DEMO / "model.safetensors").read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def server():
    proc = ServeProcess()
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


@pytest.fixture(scope="module")
def key_file(tmp_path_factory) -> Tuple[Path, str]:
    path = tmp_path_factory.mktemp("auth") / "key.txt"
    path.write_text("s3cret-key-file\n  \n")
    return path, "s3cret-key-file"


@pytest.fixture(scope="module")
def auth_server(key_file):
    proc = ServeProcess(["--api-key-file", str(key_file[0])])
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


# -- /act: inputs ---------------------------------------------------------------------------------------------


def test_act_base64_png(server):
    status, headers, body = post_act(server, act_body(), {"X-Tether-Request-ID": "png-1"})
    data = ok_json((status, headers, body))
    check_actions(data)
    assert data["request_id"] == "png-1" == headers["x-tether-request-id"]
    assert data["model_hash"] == model_hash()
    assert data["inference_mode"]["backend"] == "cpu" and data["inference_mode"]["precision"] == "fp32"
    assert isinstance(data["inference_mode"]["gemm"], str) and data["inference_mode"]["gemm"]
    stages = {"total", "queue", "preprocess", "vision", "prefix", "denoise", "postprocess", "predict"}
    assert set(data["latency_ms"]) == stages
    assert all(v >= 0 for v in data["latency_ms"].values())
    assert data["latency_ms"]["total"] >= data["latency_ms"]["predict"] >= data["latency_ms"]["denoise"]
    assert data["episode_id"] is None and data["warnings"] == [] and data["batch_size"] >= 1


def test_act_matches_predict_cli(server):
    """The server and `tether predict` run the same engine: same inputs and seed give the same chunk."""
    out = subprocess.run(
        [str(binary_path()), "predict", str(DEMO), "--image", f"front={SAMPLE_PNG}", "--state",
         ",".join(f"{v:g}" for v in STATE), "--instruction", INSTRUCTION, "--seed", "7", "--json"],
        capture_output=True, text=True, timeout=60, check=True,
    )
    cli = np.asarray(json.loads(out.stdout)["actions"], dtype=np.float32)
    served = check_actions(ok_json(post_act(server, act_body(seed=7))))
    np.testing.assert_array_equal(served, cli)


def test_act_base64_jpeg(server):
    jpeg = base64.b64encode(JPEG_PATH.read_bytes()).decode()
    data = ok_json(post_act(server, act_body(image=jpeg)))
    check_actions(data)
    assert data["warnings"] == []


def test_png_and_raw_array_of_the_same_pixels_agree(server):
    pixels = decode_png_rgb8(SAMPLE_BYTES)
    raw = {"data": base64.b64encode(pixels.tobytes()).decode(), "shape": list(pixels.shape)}
    from_png = check_actions(ok_json(post_act(server, act_body(seed=11))))
    from_raw = check_actions(ok_json(post_act(server, act_body(seed=11, image=raw))))
    np.testing.assert_array_equal(from_png, from_raw)
    # And a synthetic frame through the client's numpy path and through a PNG of it.
    frame = np.random.default_rng(3).integers(0, 256, size=(37, 53, 3), dtype=np.uint8)
    with TetherClient(server.url, api_key="", timeout=60) as client:
        a = client.act(frame, state=STATE, instruction=INSTRUCTION, seed=5)
        b = client.act(encode_png(frame), state=STATE, instruction=INSTRUCTION, seed=5)
    assert a.actions.shape == (50, 6)
    np.testing.assert_array_equal(a.actions, b.actions)


def test_msgpack_and_json_bodies_agree(server):
    import msgpack

    frame = np.random.default_rng(4).integers(0, 256, size=(224, 224, 3), dtype=np.uint8)
    with TetherClient(server.url, api_key="", timeout=60, body_format="msgpack") as binary, \
            TetherClient(server.url, api_key="", timeout=60, body_format="json") as text:
        a = binary.act(frame, state=STATE, instruction=INSTRUCTION, seed=5, request_id="mp-1")
        b = text.act(frame, state=STATE, instruction=INSTRUCTION, seed=5)
        from_png = binary.act(SAMPLE_BYTES, state=STATE, instruction=INSTRUCTION, seed=5)
    np.testing.assert_array_equal(a.actions, b.actions)
    assert a.request_id == "mp-1" and a.latency_ms["total"] > 0 and from_png.actions.shape == (50, 6)
    # The answer follows Accept: a msgpack map with float32 actions, or JSON.
    body = msgpack.packb({"instruction": INSTRUCTION, "state": STATE, "image": SAMPLE_BYTES, "seed": 7})
    for accept, decode in (("application/msgpack", msgpack.unpackb), ("application/json", json.loads)):
        status, headers, raw = post_act(server, body, {"Content-Type": "application/msgpack", "Accept": accept})
        assert status == 200 and headers["content-type"] == accept
        check_actions(decode(raw))


@pytest.mark.parametrize(
    "body, code",
    [
        (b"\xc1", "bad_msgpack"),
        (b"\x92\x01\x02", "bad_msgpack"),  # an array, not a map
        (b"\x82\xabinstruction", "bad_msgpack"),  # truncated
        ("json", "bad_msgpack"),  # JSON sent as msgpack
        ("instruction-int", "invalid_field"),
        ("state-str", "invalid_field"),
        ("api_key", "unknown_field"),  # the key travels as a header over HTTP
    ],
    ids=["never-used-byte", "array", "truncated", "json", "instruction-int", "state-str", "api_key"],
)
def test_bad_msgpack_bodies_are_refused_and_the_server_keeps_serving(server, body, code):
    import msgpack

    fields = {"instruction": INSTRUCTION, "state": STATE, "image": SAMPLE_BYTES}
    if body == "json":
        body = act_body()
    elif body == "instruction-int":
        body = msgpack.packb(dict(fields, instruction=3))
    elif body == "state-str":
        body = msgpack.packb(dict(fields, state="0,90"))
    elif body == "api_key":
        body = msgpack.packb(dict(fields, api_key="k"))
    expect_error(post_act(server, body, {"Content-Type": "application/msgpack"}), 400, code)
    status, headers, raw = post_act(server, body, {"Content-Type": "application/msgpack", "Accept": "application/msgpack"})
    assert status == 400 and headers["content-type"] == "application/msgpack"
    assert msgpack.unpackb(raw)["error"]["code"] == code
    assert check_actions(ok_json(post_act(server, act_body(seed=3)))).shape == (50, 6)


def test_huge_msgpack_body_is_answered_413(server):
    frame = np.zeros((2048, 4096, 3), dtype=np.uint8)  # 24 MiB of raw bytes against the default 16 MiB
    with TetherClient(server.url, api_key="", timeout=60, body_format="msgpack") as client:
        with pytest.raises(InvalidRequestError) as info:
            client.act(frame, state=STATE, instruction=INSTRUCTION)
        assert (info.value.status, info.value.code) == (413, "body_too_large")
        assert client.act(tiny_frame(), state=STATE, instruction=INSTRUCTION).actions.shape == (50, 6)


def test_image_and_images_short_and_full_names_agree(server):
    results = [
        check_actions(ok_json(post_act(server, act_body(seed=3)))),
        check_actions(ok_json(post_act(server, act_body(seed=3, image=_UNSET, images={"front": SAMPLE_B64})))),
        check_actions(ok_json(post_act(server, act_body(seed=3, image=_UNSET, images={CAMERA: SAMPLE_B64})))),
    ]
    np.testing.assert_array_equal(results[0], results[1])
    np.testing.assert_array_equal(results[0], results[2])


def test_no_image_at_all_is_refused(server):
    # Upstream lerobot refuses a batch without any camera image; so does the server.
    expect_error(post_act(server, act_body(image=_UNSET)), 400, "missing_field")
    expect_error(post_act(server, act_body(image=_UNSET, images={})), 400, "missing_field")


@pytest.fixture(scope="module")
def two_camera_server(tmp_path_factory):
    """The demo checkpoint declaring a second camera, `wrist` (the vision tower is shared by all cameras, so
    the weights fit as they are)."""
    ckpt = tmp_path_factory.mktemp("two_cam") / "smolvla-two-cam"
    shutil.copytree(DEMO, ckpt)
    wrist = {"type": "VISUAL", "shape": [3, 480, 640]}
    config = json.loads((ckpt / "config.json").read_text())
    config["input_features"] = {CAMERA: config["input_features"][CAMERA], "observation.images.wrist": wrist,
                                **{k: v for k, v in config["input_features"].items() if k != CAMERA}}
    (ckpt / "config.json").write_text(json.dumps(config, indent=2))
    pre = json.loads((ckpt / "policy_preprocessor.json").read_text())
    for step in pre["steps"]:
        if "features" in step.get("config", {}):
            step["config"]["features"]["observation.images.wrist"] = wrist
    (ckpt / "policy_preprocessor.json").write_text(json.dumps(pre, indent=2))
    proc = ServeProcess(checkpoint=ckpt)
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


def test_missing_camera_runs_with_a_warning(two_camera_server):
    cfg = json.loads(request(two_camera_server.port, "GET", "/config")[2])
    assert cfg["cameras"] == [CAMERA, "observation.images.wrist"]
    assert cfg["stages"] == ["preprocess", "vision", "prefix", "denoise"] and cfg["missing_camera_rule"]
    data = ok_json(post_act(two_camera_server, act_body(image=_UNSET, images={"front": SAMPLE_B64})))
    check_actions(data)
    assert len(data["warnings"]) == 1 and "wrist" in data["warnings"][0], data["warnings"]
    # "image" means the first camera.
    via_image = ok_json(post_act(two_camera_server, act_body()))
    np.testing.assert_array_equal(check_actions(via_image), check_actions(data))
    assert via_image["warnings"] == data["warnings"]
    both = ok_json(post_act(two_camera_server, act_body(image=_UNSET, images={"front": SAMPLE_B64,
                                                                              "wrist": SAMPLE_B64})))
    assert both["warnings"] == []
    assert not np.array_equal(check_actions(both), check_actions(data))


def test_seed_reproducibility(server):
    a = check_actions(ok_json(post_act(server, act_body(seed=1234))))
    b = check_actions(ok_json(post_act(server, act_body(seed=1234))))
    c = check_actions(ok_json(post_act(server, act_body(seed=1235))))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # Without a seed the noise comes from the request id: the same id repeats, another id differs.
    d = check_actions(ok_json(post_act(server, act_body(seed=_UNSET), {"X-Tether-Request-ID": "seedless-1"})))
    e = check_actions(ok_json(post_act(server, act_body(seed=_UNSET), {"X-Tether-Request-ID": "seedless-1"})))
    f = check_actions(ok_json(post_act(server, act_body(seed=_UNSET), {"X-Tether-Request-ID": "seedless-2"})))
    np.testing.assert_array_equal(d, e)
    assert not np.array_equal(d, f)


def test_episode_id_is_echoed(server):
    with TetherClient(server.url, api_key="", timeout=60) as client:
        with client.episode() as ep:
            r1 = client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION)
            r2 = client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION)
        r3 = client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION)
    assert r1.episode_id == r2.episode_id == ep.episode_id
    assert r3.episode_id is None


def test_client_keeps_one_connection(server):
    with TetherClient(server.url, api_key="", timeout=60) as client:
        client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION)
        sock = client._conn.sock  # type: ignore[union-attr]
        for _ in range(3):
            client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION)
            client.health()
        assert client._conn is not None and client._conn.sock is sock


def test_large_raw_frame_under_the_default_limit(server):
    frame = np.full((1080, 1920, 3), 127, dtype=np.uint8)  # 6 MiB raw, 8 MiB as base64
    with TetherClient(server.url, api_key="", timeout=60) as client:
        result = client.act(frame, state=STATE, instruction=INSTRUCTION, seed=1)
    assert result.actions.shape == (50, 6)


def test_body_over_the_default_limit_is_answered_413(server):
    # 24 MiB of base64 against the default 16 MiB: the server answers early; the client still reads that answer.
    frame = np.zeros((2048, 4096, 3), dtype=np.uint8)
    with TetherClient(server.url, api_key="", timeout=60) as client:
        with pytest.raises(InvalidRequestError) as info:
            client.act(frame, state=STATE, instruction=INSTRUCTION, request_id="big-1")
        assert (info.value.status, info.value.code) == (413, "body_too_large")
        assert client.act(tiny_frame(), state=STATE, instruction=INSTRUCTION).actions.shape == (50, 6)
    # The headers were read whole, so the 413 carries the client's request id like every other answer.
    assert info.value.request_id == "big-1", f"413 answered with request id {info.value.request_id!r}"


# -- other endpoints ------------------------------------------------------------------------------------------


def test_health_ready_live(server):
    status, headers, body = request(server.port, "GET", "/health")
    assert status == 200
    assert json.loads(body) == {"status": "ok", "state": "ready", "model_hash": model_hash()}
    assert REQUEST_ID_RE.match(headers["x-tether-request-id"])
    status, _, body = request(server.port, "GET", "/ready")
    assert (status, json.loads(body)) == (200, {"ready": True})
    status, _, body = request(server.port, "GET", "/live")
    assert (status, json.loads(body)) == (200, {"live": True})
    with TetherClient(server.url, api_key="", timeout=60) as client:
        assert client.ready() and client.live() and client.health()["state"] == "ready"


def test_config_fields(server):
    status, _, body = request(server.port, "GET", "/config")
    assert status == 200, body
    cfg = json.loads(body)
    assert cfg["family"] == "smolvla"
    assert cfg["cameras"] == [CAMERA]
    assert (cfg["state_dim"], cfg["action_dim"], cfg["chunk_size"], cfg["num_steps"]) == (6, 6, 50, 10)
    # A lerobot checkpoint: one group of each, named after its features, and no modality config of its own.
    assert cfg["state_groups"] == [{"name": "state", "dim": 6}]
    assert cfg["action_groups"] == [{"name": "action", "dim": 6}]
    assert cfg["modality_config"] is None
    assert isinstance(cfg["normalization"], list) and cfg["normalization"]
    assert all(isinstance(line, str) for line in cfg["normalization"])
    assert isinstance(cfg["weights_dtype"], str) and cfg["weights_dtype"]
    assert cfg["model_hash"] == model_hash()
    limits = cfg["limits"]
    defaults = {"max_batch": 8, "batch_timeout_ms": 0, "max_queue": 64, "max_body_bytes": 16777216}
    for name, value in defaults.items():
        assert limits[name] == value, (name, limits)


def test_metrics_names_and_counters_move(server):
    before_text = request(server.port, "GET", "/metrics")
    assert before_text[0] == 200
    assert before_text[1]["content-type"].startswith("text/plain")
    text = before_text[2].decode()
    before = parse_metrics(text)
    for name in ("tether_requests_total", "tether_request_duration_seconds_bucket",
                 "tether_request_duration_seconds_sum", "tether_request_duration_seconds_count",
                 "tether_queue_depth", "tether_batch_size_bucket", "tether_batch_size_count", "tether_build_info",
                 "tether_model_ready"):
        assert any(n == name for n, _ in before), f"{name} missing from /metrics"
    for stage in ("total", "queue", "preprocess", "vision", "prefix", "denoise", "postprocess"):
        assert metric(before, "tether_request_duration_seconds_count", stage=stage) >= 0
        assert any(n == "tether_request_duration_seconds_bucket" and ("stage", stage) in ls for n, ls in before), stage
    assert metric(before, "tether_model_ready") == 1
    build = [ls for n, ls in before if n == "tether_build_info"]
    assert build and {"version", "gemm"} <= {k for k, _ in build[0]}
    assert re.search(r"(?m)^# TYPE tether_request_duration_seconds histogram$", text)
    assert re.search(r"(?m)^# TYPE tether_batch_size histogram$", text)
    assert re.search(r"(?m)^# TYPE tether_queue_depth gauge$", text)

    ok_json(post_act(server, act_body()))
    expect_error(post_act(server, b"{"), 400, "bad_json")
    after = parse_metrics(request(server.port, "GET", "/metrics")[2].decode())
    assert metric(after, "tether_requests_total", endpoint="/act", status="200") == metric(
        before, "tether_requests_total", endpoint="/act", status="200") + 1
    assert metric(after, "tether_requests_total", endpoint="/act", status="400") == metric(
        before, "tether_requests_total", endpoint="/act", status="400") + 1
    for stage in ("total", "denoise"):
        assert metric(after, "tether_request_duration_seconds_count", stage=stage) == metric(
            before, "tether_request_duration_seconds_count", stage=stage) + 1
    assert metric(after, "tether_request_duration_seconds_sum", stage="total") > metric(
        before, "tether_request_duration_seconds_sum", stage="total")
    # Durations are in seconds: one demo inference is far below 10 s.
    added = metric(after, "tether_request_duration_seconds_sum", stage="total") - metric(
        before, "tether_request_duration_seconds_sum", stage="total")
    assert 0 < added < 10
    assert metric(after, "tether_batch_size_count") >= metric(before, "tether_batch_size_count") + 1
    assert metric(after, "tether_queue_depth") == 0


# -- request ids ----------------------------------------------------------------------------------------------


def test_request_id_echo_rules(server):
    def rid(headers: Dict[str, str], path: str = "/health") -> Tuple[str, Dict[str, Any]]:
        if path == "/act":
            status, h, body = post_act(server, act_body(), headers)
        else:
            status, h, body = request(server.port, "GET", path, headers=headers)
        return h["x-tether-request-id"], json.loads(body)

    assert rid({"X-Tether-Request-ID": "robot-7.step:12_a-b"})[0] == "robot-7.step:12_a-b"
    assert rid({"X-Request-ID": "upstream-42"})[0] == "upstream-42"
    assert rid({"X-Tether-Request-ID": "wins", "X-Request-ID": "loses"})[0] == "wins"
    for bad in ("has space", "x" * 129, "semi;colon", "slash/no"):
        got = rid({"X-Request-ID": bad})[0]
        assert got != bad and REQUEST_ID_RE.match(got), (bad, got)
    assert len(rid({"X-Request-ID": "y" * 128})[0]) == 128
    generated = {rid({})[0] for _ in range(5)}
    assert len(generated) == 5 and all(REQUEST_ID_RE.match(g) for g in generated)
    got, body = rid({"X-Request-ID": "act-via-x-request-id"}, "/act")
    assert got == body["request_id"] == "act-via-x-request-id"
    # Errors carry the id too.
    status, h, _ = request(server.port, "GET", "/nope", headers={"X-Tether-Request-ID": "err-1"})
    assert (status, h["x-tether-request-id"]) == (404, "err-1")
    status, h, _ = post_act(server, b"not json", {"X-Request-ID": "err-2"})
    assert (status, h["x-tether-request-id"]) == (400, "err-2")


def test_invalid_tether_request_id_is_replaced(server):
    _, h, _ = request(server.port, "GET", "/health", headers={"X-Tether-Request-ID": "bad id with spaces"})
    assert h["x-tether-request-id"] != "bad id with spaces" and REQUEST_ID_RE.match(h["x-tether-request-id"])


# -- errors ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, body, code",
    [
        ("truncated json", b'{"instruction": "x", "state": [1,', "bad_json"),
        ("not json", b"hello", "bad_json"),
        ("empty body", b"", "bad_json"),
        ("top level array", b"[1, 2, 3]", None),
        ("missing instruction", act_body(instruction=_UNSET), "missing_field"),
        ("missing state", act_body(state=_UNSET), "missing_field"),
        ("instruction not a string", act_body(instruction=42), "invalid_field"),
        ("state too short", act_body(state=STATE[:5]), "invalid_state"),
        ("state too long", act_body(state=STATE + [1.0]), "invalid_state"),
        ("state empty", act_body(state=[]), "invalid_state"),
        ("state huge number (inf)", act_body().replace(b'"state": [0.0,', b'"state": [1e999,'), "invalid_state"),
        ("state negative huge (-inf)", act_body().replace(b'"state": [0.0,', b'"state": [-1e999,'),
         "invalid_state"),
        ("state of strings", act_body(state=["a"] * 6), None),
        ("state not a list", act_body(state=3.0), None),
        ("image not base64", act_body(image="@@@ not base64 @@@"), "invalid_field"),
        ("image not an image", act_body(image=base64.b64encode(b"hello world, not a picture").decode()),
         "invalid_image"),
        ("truncated png", act_body(image=base64.b64encode(
            (FIXTURE_IMAGES / "bad" / "truncated.png").read_bytes()).decode()), "invalid_image"),
        ("truncated jpeg", act_body(image=base64.b64encode(
            (FIXTURE_IMAGES / "bad" / "truncated.jpg").read_bytes()).decode()), "invalid_image"),
        ("raw wrong length", act_body(image={"data": base64.b64encode(b"\0" * 10).decode(), "shape": [2, 2, 3]}),
         "invalid_field"),
        ("raw four channels", act_body(image={"data": base64.b64encode(b"\0" * 16).decode(), "shape": [2, 2, 4]}),
         "invalid_field"),
        ("raw shape missing", act_body(image={"data": base64.b64encode(b"\0" * 12).decode()}), None),
        ("raw zero size", act_body(image={"data": "", "shape": [0, 0, 3]}), "invalid_field"),
        ("image a number", act_body(image=5), "invalid_field"),
        ("images not an object", act_body(image=_UNSET, images=[SAMPLE_B64]), "invalid_field"),
        ("image and images", act_body(images={"front": SAMPLE_B64}), None),
        ("unknown camera", act_body(image=_UNSET, images={"left": SAMPLE_B64}), "unknown_camera"),
        ("unknown camera full name", act_body(image=_UNSET, images={"observation.images.left": SAMPLE_B64}),
         "unknown_camera"),
        ("unknown field", act_body(temperature=0.5), "unknown_field"),
        ("seed negative", act_body(seed=-1), "invalid_field"),
        ("seed not integer", act_body(seed=1.5), "invalid_field"),
        ("seed string", act_body(seed="7"), "invalid_field"),
        ("episode id not a string", act_body(episode_id=12), "invalid_field"),
        ("seed over uint64", act_body(seed=2**64), "invalid_field"),
        ("state of booleans", act_body(state=[True] * 6), "invalid_field"),
        ("camera value null", act_body(image=_UNSET, images={"front": None}), "invalid_field"),
        ("raw extra key", act_body(image={"data": "gICA", "shape": [1, 1, 3], "x": 1}), "invalid_field"),
        ("raw shape 2-d", act_body(image={"data": "gICA", "shape": [1, 3]}), "invalid_field"),
        ("raw shape negative", act_body(image={"data": "gICA", "shape": [-1, 1, 3]}), "invalid_field"),
        # A huge declared shape must be refused before anything is allocated.
        ("raw shape huge", act_body(image={"data": "gICA", "shape": [100000, 100000, 3]}), "invalid_field"),
        ("jpeg bomb", act_body(image=_b64_file("bad/bomb_3600mp.jpg")), "invalid_image"),
        ("png bomb", act_body(image=_b64_file("bad/bomb_400mp.png")), "invalid_image"),
        ("cmyk jpeg", act_body(image=_b64_file("bad/cmyk.jpg")), "invalid_image"),
        ("gif", act_body(image=_b64_file("bad/not_an_image.gif")), "invalid_image"),
        ("json nested deep", act_body()[:-1] + b', "x": ' + b"[" * 5000 + b"]" * 5000 + b"}", None),
        ("trailing garbage", act_body() + b"xyz", "bad_json"),
        ("invalid utf-8", act_body(instruction="\u00ff").replace(b"\\u00ff", b"\xff\xfe"), "bad_json"),
    ],
    ids=lambda v: v if isinstance(v, str) and len(v) < 40 else "",
)
def test_act_400_codes(server, name, body, code):
    expect_error(post_act(server, body), 400, code)


def test_accepted_edge_values(server):
    check_actions(ok_json(post_act(server, act_body(seed=2**64 - 1))))
    check_actions(ok_json(post_act(server, act_body(instruction=""))))
    check_actions(ok_json(post_act(server, act_body(instruction="pick up the red cube " * 500))))
    check_actions(ok_json(post_act(server, act_body(image=_b64_file("images/gray8.png")))))
    data = ok_json(post_act(server, act_body(episode_id="ep-" + "e" * 1000)))
    assert data["episode_id"] == "ep-" + "e" * 1000


def test_nan_token_is_rejected(server):
    # JSON has no NaN literal: a strict parser reports bad_json; a lenient one must still refuse the value.
    body = act_body().replace(b'"state": [0.0,', b'"state": [NaN,')
    assert b"NaN" in body
    err = expect_error(post_act(server, body), 400)
    assert err["code"] in ("bad_json", "invalid_state"), err
    body = act_body().replace(b'"state": [0.0,', b'"state": [Infinity,')
    err = expect_error(post_act(server, body), 400)
    assert err["code"] in ("bad_json", "invalid_state"), err


def test_wrong_method_and_unknown_path(server):
    expect_error(request(server.port, "GET", "/act"), 405, "method_not_allowed")
    expect_error(request(server.port, "POST", "/health", b"{}"), 405, "method_not_allowed")
    expect_error(request(server.port, "DELETE", "/config"), 405, "method_not_allowed")
    expect_error(request(server.port, "PUT", "/act", act_body()), 405, "method_not_allowed")
    expect_error(request(server.port, "GET", "/nope"), 404, "not_found")
    expect_error(request(server.port, "POST", "/act/extra", act_body()), 404, "not_found")
    expect_error(request(server.port, "GET", "/"), 404, "not_found")


def test_header_over_the_default_limit(server):
    # 20 000 bytes of headers against the default 16 384.
    data = (
        b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Padding: " + b"a" * 20000 + b"\r\n\r\n"
    )
    status, headers, body = parse_raw_response(raw_exchange(server.port, data))
    expect_error((status, headers, body), 431, "header_too_large")
    # A request just under it still works.
    status, _, _ = request(server.port, "GET", "/health", headers={"X-Padding": "a" * 15000})
    assert status == 200


def test_client_exceptions_from_the_real_server(server):
    with TetherClient(server.url, api_key="", timeout=60) as client:
        with pytest.raises(InvalidRequestError) as info:
            client.act(images={"left": SAMPLE_PNG}, state=STATE, instruction=INSTRUCTION, request_id="cl-1")
        assert (info.value.status, info.value.code, info.value.request_id) == (400, "unknown_camera", "cl-1")
        with pytest.raises(InvalidRequestError) as info:
            client.act(SAMPLE_PNG, state=STATE[:3], instruction=INSTRUCTION)
        assert info.value.code == "invalid_state" and "state" in info.value.message
        # The connection survives the errors.
        assert client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION).actions.shape == (50, 6)


def test_server_still_healthy_after_errors(server):
    for _ in range(3):
        expect_error(post_act(server, b"\xff\xfe garbage"), 400)
    assert request(server.port, "GET", "/health")[0] == 200
    check_actions(ok_json(post_act(server, act_body())))


# -- limits ---------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_server():
    proc = ServeProcess(["--max-body-bytes", "4096", "--max-header-bytes", "2048"])
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


def test_body_limit(small_server):
    tiny = {"data": base64.b64encode(b"\x80" * 12).decode(), "shape": [2, 2, 3]}
    small = act_body(image=tiny)
    assert len(small) < 4096
    check_actions(ok_json(post_act(small_server, small)))
    big = act_body(image={"data": base64.b64encode(b"\x80" * 3000 * 3).decode(), "shape": [50, 60, 3]})
    assert len(big) > 4096
    expect_error(post_act(small_server, big), 413, "body_too_large")
    # The limit holds for a body sent without Content-Length too (chunked).
    chunked = (
        b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
        + b"".join(b"%x\r\n%s\r\n" % (len(part), part) for part in [big[i : i + 1000] for i in range(0, len(big), 1000)])
        + b"0\r\n\r\n"
    )
    expect_error(parse_raw_response(raw_exchange(small_server.port, chunked)), 413, "body_too_large")
    limits = json.loads(request(small_server.port, "GET", "/config")[2])["limits"]
    assert limits["max_body_bytes"] == 4096
    with TetherClient(small_server.url, api_key="", timeout=60) as client:
        with pytest.raises(InvalidRequestError) as info:
            client.act(np.zeros((64, 64, 3), np.uint8), state=STATE, instruction=INSTRUCTION)
        assert (info.value.status, info.value.code) == (413, "body_too_large")


def test_header_limit_flag(small_server):
    assert request(small_server.port, "GET", "/health", headers={"X-Padding": "a" * 1000})[0] == 200
    data = b"GET /health HTTP/1.1\r\nHost: x\r\nX-Padding: " + b"a" * 3000 + b"\r\n\r\n"
    expect_error(parse_raw_response(raw_exchange(small_server.port, data)), 431, "header_too_large")


# -- auth -----------------------------------------------------------------------------------------------------


def _auth_checks(server: ServeProcess, key: str) -> None:
    before = parse_metrics(request(server.port, "GET", "/metrics")[2].decode())
    expect_error(post_act(server, act_body()), 401, "unauthorized")
    expect_error(post_act(server, act_body(), {"Authorization": "Bearer wrong"}), 401, "unauthorized")
    expect_error(post_act(server, act_body(), {"Authorization": f"Bearer {key}x"}), 401, "unauthorized")
    expect_error(post_act(server, act_body(), {"Authorization": key}), 401, "unauthorized")
    expect_error(post_act(server, act_body(), {"X-Tether-Key": key[:-1]}), 401, "unauthorized")
    expect_error(post_act(server, act_body(), {"X-Tether-Key": ""}), 401, "unauthorized")
    # Auth is checked before the body: a malformed body without a key is still 401.
    expect_error(post_act(server, b"{", {"X-Tether-Request-ID": "noauth"}), 401, "unauthorized")
    expect_error(request(server.port, "GET", "/config"), 401, "unauthorized")
    mid = parse_metrics(request(server.port, "GET", "/metrics")[2].decode())
    # Nothing ran for the refused requests.
    for stage in ("total", "preprocess", "denoise"):
        assert metric(mid, "tether_request_duration_seconds_count", stage=stage) == metric(
            before, "tether_request_duration_seconds_count", stage=stage), stage
    assert metric(mid, "tether_batch_size_count") == metric(before, "tether_batch_size_count")
    assert metric(mid, "tether_requests_total", endpoint="/act", status="401") == metric(
        before, "tether_requests_total", endpoint="/act", status="401") + 7

    check_actions(ok_json(post_act(server, act_body(), {"Authorization": f"Bearer {key}"})))
    check_actions(ok_json(post_act(server, act_body(), {"X-Tether-Key": key})))
    status, _, body = request(server.port, "GET", "/config", headers={"X-Tether-Key": key})
    assert status == 200 and json.loads(body)["family"] == "smolvla"
    for path in ("/health", "/ready", "/live", "/metrics"):
        assert request(server.port, "GET", path)[0] == 200, path
    after = parse_metrics(request(server.port, "GET", "/metrics")[2].decode())
    assert metric(after, "tether_request_duration_seconds_count", stage="total") == metric(
        before, "tether_request_duration_seconds_count", stage="total") + 2

    with TetherClient(server.url, api_key=key, timeout=60) as client:
        assert client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION).actions.shape == (50, 6)
        assert client.config()["state_dim"] == 6
    with TetherClient(server.url, api_key="nope", timeout=60) as client:
        with pytest.raises(AuthenticationError) as info:
            client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION)
        assert (info.value.status, info.value.code) == (401, "unauthorized")
        assert client.health()["state"] == "ready"  # public


def test_auth_with_key_file(auth_server, key_file):
    _auth_checks(auth_server, key_file[1])


def test_auth_with_env_key():
    proc = ServeProcess(env={"TETHER_API_KEY": "env-key-123"})
    try:
        _auth_checks(proc, "env-key-123")
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_no_key_means_open(server):
    check_actions(ok_json(post_act(server, act_body(), {"Authorization": "Bearer anything"})))


# -- load, shutdown, warm-up ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_bounded_burst_gives_answers_or_clean_queue_full():
    proc = ServeProcess(["--max-queue", "4", "--max-batch", "4"])
    try:
        reference = check_actions(ok_json(post_act(proc, act_body(seed=99))))
        body = act_body(seed=99)

        def one(i: int) -> Tuple[int, Dict[str, str], bytes]:
            return post_act(proc, body, {"X-Tether-Request-ID": f"burst-{i}"})

        start = time.monotonic()
        with concurrent.futures.ThreadPoolExecutor(16) as pool:
            results = list(pool.map(one, range(64), timeout=120))
        elapsed = time.monotonic() - start
        ok, busy, batch_sizes = 0, 0, []
        for i, (status, headers, raw) in enumerate(results):
            assert headers["x-tether-request-id"] == f"burst-{i}"
            if status == 200:
                data = json.loads(raw)
                # Batched with others or not, the same seed and inputs give the same chunk.
                np.testing.assert_array_equal(check_actions(data), reference)
                batch_sizes.append(data["batch_size"])
                ok += 1
            else:
                expect_error((status, headers, raw), 503, "queue_full")
                assert headers.get("retry-after") == "1"
                busy += 1
        assert ok + busy == 64 and ok > 0
        assert elapsed < 120
        assert max(batch_sizes) <= 4
        samples = parse_metrics(request(proc.port, "GET", "/metrics")[2].decode())
        assert metric(samples, "tether_requests_total", endpoint="/act", status="503") == busy
        assert metric(samples, "tether_queue_depth") == 0
        print(f"burst: {ok} answered, {busy} queue_full, max batch {max(batch_sizes)}, {elapsed:.2f} s")

        # Retrying clients get every request through (a retry budget that outlasts a busy machine: each retry
        # waits the server's Retry-After of 1 s).
        def via_client(i: int) -> np.ndarray:
            with TetherClient(proc.url, api_key="", retries=200, max_retry_wait=100, timeout=60) as client:
                return client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION, seed=99).actions

        with concurrent.futures.ThreadPoolExecutor(12) as pool:
            for actions in pool.map(via_client, range(12), timeout=240):
                np.testing.assert_array_equal(actions, reference)
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


@pytest.mark.slow
def test_sigterm_finishes_in_flight_requests_and_exits_0():
    proc = ServeProcess(["--max-batch", "2"])
    n = 12
    body = act_body(seed=5)
    request_bytes = (
        b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: %d\r\n\r\n" % len(body)
        + body
    )
    socks = [socket.create_connection(("127.0.0.1", proc.port), timeout=30) for _ in range(n)]
    try:
        for s in socks:
            s.sendall(request_bytes)
        # The first answers prove the requests are being served; the others are then queued or running.
        first = socks[0].recv(1, socket.MSG_PEEK)
        assert first, "no answer to the first request"
        proc.proc.send_signal(signal.SIGTERM)
        statuses = []
        for s in socks:
            data = b""
            while not _complete(data):
                chunk = s.recv(65536)
                if not chunk:
                    break
                data += chunk
            assert data, "connection closed without an answer"
            status, _, raw = parse_raw_response(data)
            statuses.append(status)
            if status == 200:
                check_actions(json.loads(raw))
        assert statuses == [200] * n, statuses
        rc = proc.proc.wait(timeout=20)
        assert rc == 0, proc.stderr_tail()
        # Nothing listens any more.
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", proc.port), timeout=2).close()
    finally:
        for s in socks:
            s.close()
        proc.kill()


def _complete(data: bytes) -> bool:
    head, sep, rest = data.partition(b"\r\n\r\n")
    m = re.search(rb"(?im)^content-length:\s*(\d+)", head)
    return bool(sep) and m is not None and len(rest) >= int(m.group(1))


@pytest.mark.slow
def test_sigterm_idle_exits_0_and_sigint_too():
    for sig in (signal.SIGTERM, signal.SIGINT):
        proc = ServeProcess()
        start = time.monotonic()
        assert proc.stop(sig) == 0, proc.stderr_tail()
        assert time.monotonic() - start < 5


@pytest.mark.slow
def test_health_states_and_client_retry_while_warming():
    """Right after the socket is bound the model may still be loading or warming: /health says 503 with a state
    until then, /act answers 503 not_ready, and the client's retries carry a request through."""
    proc = ServeProcess(wait_ready=False)
    try:
        seen: List[Tuple[int, str]] = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            status, headers, body = request(proc.port, "GET", "/health")
            data = json.loads(body)
            assert set(data) >= {"status", "state", "model_hash"}, data
            seen.append((status, data["state"]))
            if status == 200:
                assert data["status"] == "ok" and data["state"] == "ready"
                break
            assert status == 503 and data["status"] == "unavailable", data
            assert data["state"] in ("loading", "warming"), data
            time.sleep(0.005)
        assert seen and seen[-1] == (200, "ready"), seen
        print(f"health states seen: {sorted(set(seen))}")
    finally:
        assert proc.stop() == 0, proc.stderr_tail()

    proc = ServeProcess(wait_ready=False)
    try:
        not_ready_seen = 0
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            status, headers, body = post_act(proc, act_body(image={"data": "gICA", "shape": [1, 1, 3]}))
            if status == 200:
                break
            expect_error((status, headers, body), 503, "not_ready")
            assert headers.get("retry-after") == "1"
            not_ready_seen += 1
            time.sleep(0.002)
        assert status == 200
        print(f"/act answered 503 not_ready {not_ready_seen} times before ready")
    finally:
        assert proc.stop() == 0, proc.stderr_tail()

    proc = ServeProcess(wait_ready=False)
    try:
        with TetherClient(proc.url, api_key="", backoff=0.01, max_retry_wait=60, timeout=60) as client:
            result = client.act(SAMPLE_PNG, state=STATE, instruction=INSTRUCTION, seed=1)
        assert result.actions.shape == (50, 6)
        samples = parse_metrics(request(proc.port, "GET", "/metrics")[2].decode())
        not_ready = metric(samples, "tether_requests_total", endpoint="/act", status="503")
        print(f"503 answers before ready: {not_ready:g}")
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_ready_503_body_shape_while_not_ready():
    """/ready and /act before warm-up (when the window is caught) follow the contract; otherwise both are ready."""
    proc = ServeProcess(wait_ready=False)
    try:
        status, headers, body = request(proc.port, "GET", "/ready")
        if status == 503:
            assert json.loads(body) == {"ready": False}
        else:
            assert (status, json.loads(body)) == (200, {"ready": True})
        status, headers, body = post_act(proc, act_body())
        if status == 503:
            expect_error((status, headers, body), 503, "not_ready")
            assert headers.get("retry-after") == "1"
        else:
            check_actions(ok_json((status, headers, body)))
        status, _, body = request(proc.port, "GET", "/live")
        assert (status, json.loads(body)) == (200, {"live": True})
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- timeouts -------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_request_deadline_gives_408():
    # One request per forward pass and a 1 ms deadline: of a burst, those left waiting in the queue time out.
    proc = ServeProcess(["--request-timeout-ms", "1", "--max-batch", "1"])
    try:
        tiny = {"data": base64.b64encode(b"\x80" * 12).decode(), "shape": [2, 2, 3]}
        body = act_body(image=tiny)
        with concurrent.futures.ThreadPoolExecutor(8) as pool:
            results = list(pool.map(lambda i: post_act(proc, body), range(12), timeout=120))
        statuses = [r[0] for r in results]
        assert set(statuses) <= {200, 408}, statuses
        assert 408 in statuses, statuses
        for r in results:
            if r[0] == 408:
                expect_error(r, 408, "request_timeout")
            else:
                check_actions(ok_json(r))
        with TetherClient(proc.url, api_key="", retries=0, timeout=60) as client:
            with concurrent.futures.ThreadPoolExecutor(8) as pool:
                futures = [pool.submit(client.act, tiny_frame(), state=STATE, instruction="x") for _ in range(4)]
            errors = [f.exception() for f in futures if f.exception() is not None]
            assert all(isinstance(e, RequestTimeoutError) and e.code == "request_timeout" for e in errors), errors
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def tiny_frame() -> np.ndarray:
    return np.full((2, 2, 3), 128, dtype=np.uint8)


def test_read_timeout_and_idle_keep_alive():
    proc = ServeProcess(["--read-timeout-ms", "300"])
    try:
        # A body that stalls half-way: the connection is dropped after the read timeout (with a 408 if any).
        with socket.create_connection(("127.0.0.1", proc.port), timeout=5) as s:
            s.sendall(b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n{\"instruction\"")
            start = time.monotonic()
            data = b""
            while True:
                chunk = s.recv(65536)
                if not chunk:
                    break
                data += chunk
            waited = time.monotonic() - start
        assert 0.2 <= waited < 3, waited
        if data:
            expect_error(parse_raw_response(data), 408, "request_timeout")
        # Headers that never end: dropped the same way.
        with socket.create_connection(("127.0.0.1", proc.port), timeout=5) as s:
            s.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
            start = time.monotonic()
            while s.recv(65536):
                pass
            assert time.monotonic() - start < 3
        # The server closes an idle keep-alive connection; the client reopens it without failing the call.
        with TetherClient(proc.url, api_key="", timeout=60) as client:
            first = client.act(tiny_frame(), state=STATE, instruction=INSTRUCTION, seed=2)
            time.sleep(0.6)
            second = client.act(tiny_frame(), state=STATE, instruction=INSTRUCTION, seed=2)
            np.testing.assert_array_equal(first.actions, second.actions)
        assert request(proc.port, "GET", "/health")[0] == 200
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- batching and HTTP framing --------------------------------------------------------------------------------


def test_batched_requests_match_their_solo_answers():
    # A long batch window so concurrent requests share forward passes; each keeps its own seed's answer.
    proc = ServeProcess(["--batch-timeout-ms", "200", "--max-batch", "8"])
    try:
        seeds = list(range(20, 28))
        solo = {s: check_actions(ok_json(post_act(proc, act_body(seed=s)))) for s in seeds}
        barrier = threading.Barrier(len(seeds))

        def one(seed: int) -> Dict[str, Any]:
            barrier.wait(timeout=30)
            return ok_json(post_act(proc, act_body(seed=seed)))

        with concurrent.futures.ThreadPoolExecutor(len(seeds)) as pool:
            answers = dict(zip(seeds, pool.map(one, seeds, timeout=120)))
        for s in seeds:
            np.testing.assert_array_equal(check_actions(answers[s]), solo[s], err_msg=f"seed {s}")
        assert max(a["batch_size"] for a in answers.values()) > 1, [a["batch_size"] for a in answers.values()]
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_pipelined_and_chunked_requests(server):
    body = act_body(seed=4)
    one = b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: %d\r\n" % len(body)
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
        # Two requests written back to back on one connection are answered in order.
        s.sendall(one + b"X-Tether-Request-ID: pipe-1\r\n\r\n" + body + one + b"X-Tether-Request-ID: pipe-2\r\n\r\n" + body)
        data = b""
        answers = []
        while len(answers) < 2:
            chunk = s.recv(65536)
            assert chunk, f"connection closed after {len(answers)} answers"
            data += chunk
            while _complete(data):
                head, _, rest = data.partition(b"\r\n\r\n")
                length = int(re.search(rb"(?im)^content-length:\s*(\d+)", head).group(1))
                answers.append(parse_raw_response(head + b"\r\n\r\n" + rest[:length]))
                data = rest[length:]
        assert [a[1]["x-tether-request-id"] for a in answers] == ["pipe-1", "pipe-2"]
        assert [a[0] for a in answers] == [200, 200]
        np.testing.assert_array_equal(check_actions(json.loads(answers[0][2])), check_actions(json.loads(answers[1][2])))
    # A chunked body under the limit is read whole.
    chunked = (
        b"POST /act HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
        + b"".join(b"%x\r\n%s\r\n" % (len(p), p) for p in [body[i : i + 4096] for i in range(0, len(body), 4096)])
        + b"0\r\n\r\n"
    )
    status, _, raw = parse_raw_response(raw_exchange(server.port, chunked))
    assert status == 200, raw[:300]
    check_actions(json.loads(raw))
    # "Connection: close" is honoured.
    with socket.create_connection(("127.0.0.1", server.port), timeout=30) as s:
        s.sendall(b"GET /live HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        data = b""
        while True:
            chunk = s.recv(65536)
            if not chunk:
                break
            data += chunk
    assert parse_raw_response(data)[0] == 200


def test_bf16_precision_is_served_and_reported(server):
    """--precision bf16: /act and /config say so, and the chunk stays close to the fp32 server's."""
    bf16 = ServeProcess(["--precision", "bf16"])
    try:
        got = ok_json(post_act(bf16, act_body(seed=5)))
        assert got["inference_mode"]["precision"] == "bf16"
        ref = ok_json(post_act(server, act_body(seed=5)))
        assert ref["inference_mode"]["precision"] == "fp32"
        a, b = check_actions(ref), check_actions(got)
        diff = float(np.max(np.abs(a - b)))
        assert 0.0 < diff < 0.02 * float(np.max(np.abs(a))), diff
        status, _, body = request(bf16.port, "GET", "/config")
        assert status == 200 and json.loads(body)["inference_mode"]["precision"] == "bf16"
    finally:
        assert bf16.stop() == 0, bf16.stderr_tail()
