"""The openpi WebSocket transport (--openpi-port) through the real `tether serve` binary: openpi_client's own
WebsocketClientPolicy and ActionChunkBroker against the demo policy, each observation layout, and raw WebSocket
clients (the `websockets` package openpi_client uses) for the failure shape, auth, limits, clients that misbehave,
and every safety wedge as this transport sees it."""

from __future__ import annotations

import base64
import errno
import json
import os
import signal
import socket
import struct
import subprocess
import time
from typing import Any, Dict, List, Optional

import msgpack
import numpy as np
import pytest

from serve_process import DEMO, ServeProcess, binary_path, metric, parse_metrics, request

openpi_client = pytest.importorskip("openpi_client")
from openpi_client import action_chunk_broker, msgpack_numpy, websocket_client_policy  # noqa: E402
import websockets.exceptions  # noqa: E402
import websockets.sync.client  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
    # openpi_client 0.1.2 keeps the connection outside a `with` block, which websockets 14+ warns about.
    pytest.mark.filterwarnings("ignore:connect\\(\\) must be used as a context manager:DeprecationWarning"),
]

CHUNK, DIM = 50, 6
STATE = np.array([0.0, 90.0, 90.0, 45.0, 0.0, 20.0])
RNG = np.random.default_rng(0)
IMAGE = RNG.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)
WRIST = RNG.integers(0, 256, size=(48, 64, 3), dtype=np.uint8)


def libero_obs(**extra: Any) -> Dict[str, Any]:
    obs: Dict[str, Any] = {"observation/image": IMAGE, "observation/wrist_image": WRIST,
                           "observation/state": STATE, "prompt": "pick up the red cube"}
    obs.update(extra)
    return obs


def openpi_port(proc: ServeProcess) -> int:
    return proc.transport_ports["openpi"]


def uri(proc: ServeProcess) -> str:
    return f"ws://127.0.0.1:{openpi_port(proc)}"


def client(proc: ServeProcess, **kw: Any) -> websocket_client_policy.WebsocketClientPolicy:
    return websocket_client_policy.WebsocketClientPolicy("127.0.0.1", openpi_port(proc), **kw)


def raw(proc: ServeProcess, **kw: Any):
    """A plain WebSocket connection with the metadata frame already read."""
    ws = websockets.sync.client.connect(uri(proc), compression=None, max_size=None, **kw)
    meta = msgpack_numpy.unpackb(ws.recv(timeout=10))
    assert meta["server"] == "tether"
    return ws


def expect_failure(ws, mention: str, code: int = 1011) -> str:
    """openpi's failure shape: a text frame with the reason, then a close frame with `code`."""
    text = ws.recv(timeout=20)
    assert isinstance(text, str), text
    assert mention in text, text
    with pytest.raises(websockets.exceptions.ConnectionClosed) as closed:
        ws.recv(timeout=20)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == code, closed.value
    return text


def metrics_of(proc: ServeProcess) -> Dict:
    status, _, body = request(proc.port, "GET", "/metrics")
    assert status == 200
    return parse_metrics(body.decode())


def http_actions(proc: ServeProcess, seed: int) -> np.ndarray:
    body = {"instruction": "pick up the red cube", "state": STATE.tolist(), "seed": seed,
            "images": {"front": {"data": base64.b64encode(IMAGE.tobytes()).decode(), "shape": list(IMAGE.shape)}}}
    status, _, data = request(proc.port, "POST", "/act", json.dumps(body).encode(), {"Content-Type": "application/json"})
    assert status == 200, data
    return np.asarray(json.loads(data)["actions"], dtype=np.float32)


def retry_until_ok(proc: ServeProcess, obs: Dict[str, Any], tries: int = 120) -> Dict[str, Any]:
    """Infers on fresh connections (a failure closes one) until an answer comes; returns it."""
    for _ in range(tries):
        policy = client(proc)
        try:
            return policy.infer(obs)
        except RuntimeError:
            time.sleep(0.5)
        finally:
            policy._ws.close()
    raise AssertionError("no answer")


@pytest.fixture(scope="module")
def server():
    proc = ServeProcess(["--openpi-port", "0"])
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


# -- the protocol, with openpi's own client ---------------------------------------------------------------------


def test_healthz_and_non_websocket_requests(server):
    status, headers, body = request(openpi_port(server), "GET", "/healthz")
    assert status == 200 and body == b"OK\n"
    status, headers, body = request(openpi_port(server), "GET", "/")
    assert status == 426 and headers["upgrade"].lower() == "websocket" and b"openpi" in body


def test_openpi_client_infer_matches_http(server):
    policy = client(server)
    meta = policy.get_server_metadata()
    assert meta["action_horizon"] == CHUNK and meta["action_dim"] == DIM and meta["state_dim"] == DIM
    assert meta["layout"] == "auto"
    assert meta["cameras"]["libero"] == {"observation/image": "observation.images.front", "observation/wrist_image": None}
    first = policy.infer(libero_obs(seed=7))
    actions = first["actions"]
    assert isinstance(actions, np.ndarray) and actions.dtype == np.float32 and actions.shape == (CHUNK, DIM)
    assert np.all(np.isfinite(actions))
    # policy_timing is the forward pass, as openpi's server times its model; server_timing the whole request.
    assert first["policy_timing"]["infer_ms"] == first["tether"]["latency_ms"]["predict"] > 0
    assert first["policy_timing"]["infer_ms"] <= first["server_timing"]["infer_ms"]
    assert first["server_timing"]["infer_ms"] > 0 and "prev_total_ms" not in first["server_timing"]
    assert first["tether"]["request_id"] and first["tether"]["action_source"] == "model"
    second = policy.infer(libero_obs(seed=7))
    assert second["server_timing"]["prev_total_ms"] > 0
    # Same observation and seed over HTTP: the same chunk, bit for bit.
    np.testing.assert_array_equal(actions, http_actions(server, 7))
    np.testing.assert_array_equal(second["actions"], actions)


def test_action_chunk_broker_asks_once_per_horizon(server):
    before = metric(metrics_of(server), "tether_requests_total", transport="openpi", status="200")
    policy = client(server)
    chunk = policy.infer(libero_obs(seed=3))["actions"]
    broker = action_chunk_broker.ActionChunkBroker(policy, action_horizon=10)
    rows = [broker.infer(libero_obs(seed=3))["actions"] for _ in range(25)]
    assert all(r.shape == (DIM,) for r in rows)
    np.testing.assert_array_equal(np.stack(rows[:10]), chunk[:10])
    after = metric(metrics_of(server), "tether_requests_total", transport="openpi", status="200")
    assert after - before == 1 + 3  # the direct call, then steps 0, 10 and 20


def test_api_key_before_the_upgrade():
    proc = ServeProcess(["--openpi-port", "0"], env={"TETHER_API_KEY": "s3cret"})
    try:
        assert request(openpi_port(proc), "GET", "/healthz")[0] == 200  # health stays open
        policy = client(proc, api_key="s3cret")  # openpi_client sends "Authorization: Api-Key s3cret"
        assert policy.infer(libero_obs())["actions"].shape == (CHUNK, DIM)
        for headers in ({"Authorization": "Bearer s3cret"}, {"X-Tether-Key": "s3cret"}):
            ws = raw(proc, additional_headers=headers)
            ws.send(msgpack_numpy.packb(libero_obs()))
            assert msgpack_numpy.unpackb(ws.recv(timeout=20))["actions"].shape == (CHUNK, DIM)
            ws.close()
        for key in (None, "wrong"):
            with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
                client(proc, api_key=key)
            assert refused.value.response.status_code == 401
            assert json.loads(refused.value.response.body)["error"]["code"] == "unauthorized"
        assert metric(metrics_of_with_key(proc, "s3cret"), "tether_requests_total", transport="openpi",
                      endpoint="upgrade", status="401") == 2
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def metrics_of_with_key(proc: ServeProcess, key: str) -> Dict:
    status, _, body = request(proc.port, "GET", "/metrics", headers={"Authorization": f"Bearer {key}"})
    assert status == 200
    return parse_metrics(body.decode())


def test_upgrades_wait_for_the_model():
    # The warm-up pass takes the injected latency: the model is "warming" for 3 s.
    proc = ServeProcess(["--openpi-port", "0", "--inject-latency-ms", "3000"], wait_ready=False)
    try:
        status, _, body = request(openpi_port(proc), "GET", "/healthz")
        assert status == 503 and body.strip() in (b"loading", b"warming")
        with pytest.raises(websockets.exceptions.InvalidStatus) as refused:
            client(proc)
        assert refused.value.response.status_code == 503
        assert refused.value.response.headers["Retry-After"] == "1"
        assert json.loads(refused.value.response.body)["error"]["code"] == "not_ready"
        proc.wait_ready(60)
        assert request(openpi_port(proc), "GET", "/healthz")[0] == 200
        assert client(proc).get_server_metadata()["action_horizon"] == CHUNK
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- layouts ---------------------------------------------------------------------------------------------------


def test_droid_and_aloha_layouts_are_recognised(server):
    policy = client(server)
    droid = {"observation/exterior_image_1_left": IMAGE, "observation/wrist_image_left": WRIST,
             "observation/joint_position": STATE[:5], "observation/gripper_position": np.float64(STATE[5]),
             "prompt": "pick up the red cube", "seed": 7}
    expected = http_actions(server, 7)
    np.testing.assert_array_equal(policy.infer(droid)["actions"], expected)
    # aloha: nested images, channels first.
    aloha = {"images": {"cam_high": np.ascontiguousarray(IMAGE.transpose(2, 0, 1)),
                        "cam_low": np.zeros((3, 8, 8), np.uint8)},
             "state": STATE, "prompt": "pick up the red cube", "seed": 7}
    np.testing.assert_array_equal(policy.infer(aloha)["actions"], expected)
    # A float image in [0, 1] is scaled by 255 and truncated, as openpi does.
    as_float = (IMAGE.astype(np.float32) + 0.25) / np.float32(255.25)  # 255 * v truncates back to IMAGE
    np.testing.assert_array_equal(policy.infer(libero_obs(**{"observation/image": as_float}, seed=7))["actions"], expected)


def test_mapping_file_and_fixed_layout(tmp_path):
    mapping = tmp_path / "my_robot.json"
    mapping.write_text(json.dumps({"images": {"cams/top": "front"}, "state": ["arm", "gripper"],
                                   "prompt": "task", "default_prompt": "pick up the red cube", "ignore": ["debug"]}))
    proc = ServeProcess(["--openpi-port", "0", "--openpi-layout", str(mapping)])
    try:
        policy = client(proc)
        obs = {"cams": {"top": IMAGE}, "arm": STATE[:5], "gripper": STATE[5:], "debug": "x", "seed": 7}
        np.testing.assert_array_equal(policy.infer(obs)["actions"], http_actions(proc, 7))
        with pytest.raises(RuntimeError, match="observation/image"):
            policy.infer(libero_obs())
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"images": {"a": "front"}, "state": "s", "promt": "p"}))
    refused = subprocess.run([str(binary_path()), "serve", str(DEMO), "--port", "0", "--openpi-port", "0",
                              "--openpi-layout", str(bad)], capture_output=True, text=True, timeout=60)
    assert refused.returncode != 0 and "promt" in refused.stderr, refused.stderr


# -- failures: a text frame with the reason, then close 1011 ------------------------------------------------------


def test_request_errors_close_1011_and_name_the_key(server):
    bystander = raw(server)  # open across every failure below
    ws = raw(server)
    ws.send(msgpack_numpy.packb(libero_obs(**{"observation/extra": 1})))
    expect_failure(ws, "unknown key 'observation/extra'")
    ws = raw(server)
    ws.send(msgpack_numpy.packb(libero_obs(**{"observation/state": np.ones(8)})))
    expect_failure(ws, "invalid_state")
    # An object array, as msgpack-numpy would write it if it allowed one.
    ws = raw(server)
    bad = {b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "|O", b"shape": [1]}
    ws.send(msgpack.packb({**{k: v for k, v in libero_obs().items() if k != "observation/image"},
                           "observation/image": bad}, default=msgpack_numpy.pack_array))
    expect_failure(ws, "observation/image")
    for frame, mention in ((b"\xc1", "invalid_msgpack"), (b"\x92\x01", "invalid_msgpack"), ("text", "text frame")):
        ws = raw(server)
        ws.send(frame)
        expect_failure(ws, mention)
    # The server keeps serving, new connections and the one left open.
    assert client(server).infer(libero_obs())["actions"].shape == (CHUNK, DIM)
    bystander.send(msgpack_numpy.packb(libero_obs()))
    assert msgpack_numpy.unpackb(bystander.recv(timeout=20))["actions"].shape == (CHUNK, DIM)
    bystander.close()
    m = metrics_of(server)
    assert metric(m, "tether_requests_total", transport="openpi", status="400") >= 6  # the text frame included


def test_oversized_frame_closes_1009():
    proc = ServeProcess(["--openpi-port", "0", "--openpi-max-frame-bytes", "100000"])
    try:
        ws = raw(proc)
        ws.send(msgpack_numpy.packb(libero_obs()))  # about 19 kB
        assert msgpack_numpy.unpackb(ws.recv(timeout=20))["actions"].shape == (CHUNK, DIM)
        big = np.zeros((240, 320, 3), np.uint8)  # 230 kB
        ws.send(msgpack_numpy.packb(libero_obs(**{"observation/image": big})))
        expect_failure(ws, "413 frame_too_large", code=1009)
        assert metric(metrics_of(proc), "tether_requests_total", transport="openpi", status="413") == 1
        assert client(proc).infer(libero_obs())["actions"].shape == (CHUNK, DIM)
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- clients that misbehave --------------------------------------------------------------------------------------


def handshake(port: int, rcvbuf: Optional[int] = None) -> socket.socket:
    """A bare TCP WebSocket client: upgraded, then left to the test (it answers no pings)."""
    s = socket.socket()
    if rcvbuf:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(10)
    s.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += s.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    return s


def client_frame(payload: bytes, opcode: int = 0x2) -> bytes:
    """One masked client frame."""
    mask = os.urandom(4)
    n = len(payload)
    header = bytes([0x80 | opcode])
    if n < 126:
        header += bytes([0x80 | n])
    elif n < 65536:
        header += bytes([0x80 | 126]) + struct.pack(">H", n)
    else:
        header += bytes([0x80 | 127]) + struct.pack(">Q", n)
    return header + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def closed_within(s: socket.socket, seconds: float) -> bool:
    """Reads (and drops) what the server sends until it closes the connection."""
    s.settimeout(seconds)
    try:
        while s.recv(65536):
            pass
        return True
    except ConnectionResetError:
        return True
    except socket.timeout:
        return False


def test_idle_connections_are_pinged_and_dropped_when_silent():
    # Each forward pass takes 2 s, twice the idle timeout: time spent answering is not idle time.
    proc = ServeProcess(["--openpi-port", "0", "--openpi-idle-timeout-ms", "1000", "--inject-latency-ms", "2000"])
    try:
        silent = handshake(openpi_port(proc))
        live = client(proc)  # its websockets library answers the server's pings
        time.sleep(2.5)
        assert closed_within(silent, 5)
        assert live.infer(libero_obs())["actions"].shape == (CHUNK, DIM)
        assert live.infer(libero_obs())["actions"].shape == (CHUNK, DIM)
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def connection_reset(s: socket.socket) -> bool:
    """Whether the server reset the connection, read without consuming anything."""
    return s.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR) == errno.ECONNRESET


def test_a_client_that_never_reads_blocks_nobody(tmp_path):
    # Every action value clamped: each reply lists 300 guard violations (~20 kB), so the socket buffers fill after a
    # few hundred replies and the server's write blocks.
    safety = tmp_path / "limits.json"
    joints = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
    safety.write_text(json.dumps({"joint_limits": {
        j: {"has_position_limits": True, "min_position": 1000.0, "max_position": 1000.5} for j in joints}}))
    proc = ServeProcess(["--openpi-port", "0", "--write-timeout-ms", "1000", "--embodiment", "so100",
                         "--safety-config", str(safety), "--audit-log", str(tmp_path / "audit.jsonl")])
    try:
        stuck = handshake(openpi_port(proc), rcvbuf=4096)
        small = {"observation/image": IMAGE[:8, :8], "observation/wrist_image": WRIST[:8, :8]}
        frame = client_frame(msgpack_numpy.packb(libero_obs(**small)))
        stuck.settimeout(10)
        dropped = False
        try:
            stuck.sendall(frame * 2000)  # far more replies than the socket buffers hold; never read
        except (ConnectionResetError, BrokenPipeError):
            dropped = True  # already: the server stopped reading once its write blocked, then timed out
        t0 = time.monotonic()
        reply = client(proc).infer(libero_obs())
        assert reply["actions"].shape == (CHUNK, DIM) and len(reply["tether"]["guard_violations"]) >= CHUNK * DIM
        assert time.monotonic() - t0 < 10
        # The blocked write times out and the connection is dropped (reset: its requests were never read).
        deadline = time.monotonic() + 60
        while not (dropped or connection_reset(stuck)):
            assert time.monotonic() < deadline, "the stuck connection was never dropped"
            time.sleep(0.2)
        assert client(proc).infer(libero_obs())["actions"].shape == (CHUNK, DIM)
        m = metrics_of(proc)  # every request it sent was answered until then: dropped for not reading, nothing else
        assert metric(m, "tether_requests_total", transport="openpi", status="200") >= 20
        assert metric(m, "tether_requests_total", transport="openpi") == metric(
            m, "tether_requests_total", transport="openpi", status="200")
    finally:
        t0 = time.monotonic()
        assert proc.stop() == 0, proc.stderr_tail()
    assert time.monotonic() - t0 < 10 and "still in flight" not in proc.stderr_tail()


def test_ping_flood_is_dropped(server):
    s = handshake(openpi_port(server))
    ping = client_frame(b"x", opcode=0x9)
    try:
        s.sendall(ping * 2000)
    except (BrokenPipeError, ConnectionResetError):
        pass
    assert closed_within(s, 10)
    assert client(server).infer(libero_obs())["actions"].shape == (CHUNK, DIM)


def test_200_idle_connections_do_not_stop_service(server):
    idle: List[Any] = [raw(server) for _ in range(200)]
    silent = [socket.create_connection(("127.0.0.1", openpi_port(server))) for _ in range(50)]  # never upgrade
    try:
        t0 = time.monotonic()
        assert client(server).infer(libero_obs())["actions"].shape == (CHUNK, DIM)
        assert request(server.port, "GET", "/health")[0] == 200
        assert time.monotonic() - t0 < 10
        # Every idle connection is still served.
        for ws in idle[::40]:
            ws.send(msgpack_numpy.packb(libero_obs()))
            assert msgpack_numpy.unpackb(ws.recv(timeout=20))["actions"].shape == (CHUNK, DIM)
    finally:
        for ws in idle:
            ws.close()
        for s in silent:
            s.close()


def test_drain_answers_in_flight_requests_then_closes_going_away():
    proc = ServeProcess(["--openpi-port", "0", "--inject-latency-ms", "1500"])
    idle, busy = raw(proc), raw(proc)
    busy.send(msgpack_numpy.packb(libero_obs()))
    time.sleep(0.5)  # the request is in the model now
    proc.proc.send_signal(signal.SIGTERM)
    assert msgpack_numpy.unpackb(busy.recv(timeout=20))["actions"].shape == (CHUNK, DIM)
    for ws in (idle, busy):
        with pytest.raises(websockets.exceptions.ConnectionClosed) as closed:
            ws.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1001
    assert proc.stop() == 0, proc.stderr_tail()


# -- the safety wedges on this transport ------------------------------------------------------------------------


def test_guard_traces_and_metrics(tmp_path):
    safety = tmp_path / "limits.json"
    safety.write_text(json.dumps({"joint_limits": {
        "shoulder_pan": {"has_position_limits": True, "min_position": -5.0, "max_position": 5.0}}}))
    record = tmp_path / "traces"
    proc = ServeProcess(["--openpi-port", "0", "--embodiment", "so100", "--safety-config", str(safety),
                         "--record", str(record)])
    try:
        reply = client(proc).infer(libero_obs(seed=7))
        assert reply["tether"]["guard_clamped"] is True
        assert np.all(np.abs(reply["actions"][:, 0]) <= 5.0)
        assert reply["tether"]["joint_names"][0] == "shoulder_pan"
        ws = raw(proc)
        ws.send(msgpack_numpy.packb(libero_obs(**{"observation/state": np.ones(3)})))
        expect_failure(ws, "invalid_state")
        m = metrics_of(proc)
        assert metric(m, "tether_requests_total", transport="openpi", endpoint="/act", status="200") == 1
        assert metric(m, "tether_requests_total", transport="openpi", endpoint="/act", status="400") == 1
        assert metric(m, "tether_guard_clamped_total") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
    lines = [json.loads(l) for f in sorted(record.glob("trace-*.jsonl")) for l in f.read_text().splitlines()]
    assert [l["transport"] for l in lines] == ["openpi", "openpi"]
    assert lines[0]["status"] == "success" and lines[0]["request_id"] == reply["tether"]["request_id"]
    assert lines[1]["error"]["code"] == "invalid_state"


def test_deadline_answers_from_the_last_good_chunk():
    proc = ServeProcess(["--openpi-port", "0", "--inject-latency-ms", "600", "--deadline-ms", "150",
                         "--request-timeout-ms", "5000", "--control-rate-hz", "10"])
    try:
        ws = raw(proc)
        ws.send(msgpack_numpy.packb(libero_obs(seed=7)))
        expect_failure(ws, "504 deadline_exceeded")
        reply = retry_until_ok(proc, libero_obs(seed=7))  # once the late pass has finished
        assert reply["tether"]["action_source"] == "last_good" and reply["tether"]["deadline_exceeded"] is True
        assert reply["actions"].shape == (CHUNK, DIM)
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_breaker_opens(tmp_path):
    fault = tmp_path / "fail-now"
    proc = ServeProcess(["--openpi-port", "0", "--max-consecutive-crashes", "2", "--inject-failure-file", str(fault)])
    try:
        fault.touch()
        for _ in range(2):
            with pytest.raises(RuntimeError, match="500 inference_failed"):
                client(proc).infer(libero_obs())
        with pytest.raises(RuntimeError, match="503 circuit_open") as refused:
            client(proc).infer(libero_obs())
        assert "retry after 60 s" in str(refused.value)
        m = metrics_of(proc)
        assert metric(m, "tether_circuit_open") == 1
        assert metric(m, "tether_requests_total", transport="openpi", status="503") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
