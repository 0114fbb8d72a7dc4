"""Client behaviour against a scripted in-process server: encoding, keep-alive, retries, errors, episodes."""

from __future__ import annotations

import base64
import socket
import threading
import time
import uuid
import zlib
import struct
from pathlib import Path

import numpy as np
import pytest

from conftest import ACT_OK, Reply, error_reply
from tether_client import (
    AuthenticationError,
    CircuitOpenError,
    DeadlineExceededError,
    InvalidRequestError,
    ReflexClient,
    RequestTimeoutError,
    ServerBusyError,
    ServerError,
    TetherClient,
    TetherConnectionError,
    TetherError,
    TetherTimeoutError,
    encode_image,
)

STATE = [0, 90, 90, 45, 0, 20]


def tiny_png() -> bytes:
    """A valid 1x1 RGB PNG, built by hand so the tests need no imaging library."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", 1, 1, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\x00\xff\x00\x00"))
        + chunk(b"IEND", b"")
    )


def fast_client(url: str, **kw) -> TetherClient:
    kw.setdefault("backoff", 0.01)
    kw.setdefault("max_backoff", 0.05)
    kw.setdefault("api_key", "")
    return TetherClient(url, **kw)


# -- request encoding -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("body_format", ["msgpack", "json"])
def test_act_sends_raw_array_and_parses_result(fake, body_format):
    frame = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    with fast_client(fake.url, body_format=body_format) as client:
        result = client.act(frame, state=np.array(STATE, dtype=np.float32), instruction="pick", seed=7)
    sent = fake.requests[0]
    assert (sent.method, sent.path) == ("POST", "/act")
    assert sent.headers["content-type"] == f"application/{body_format}"
    body = sent.json()
    assert body["instruction"] == "pick"
    assert body["state"] == [float(v) for v in STATE]
    assert body["seed"] == 7
    assert "episode_id" not in body and "images" not in body
    assert body["image"]["shape"] == [4, 5, 3]
    if body_format == "msgpack":  # the pixels as bytes, and the answer asked for in msgpack
        assert body["image"]["data"] == frame.tobytes()
        assert sent.headers["accept"] == "application/msgpack"
    else:
        assert base64.b64decode(body["image"]["data"]) == frame.tobytes()

    assert result.actions.dtype == np.float32
    assert result.actions.shape == (50, 6) == (result.num_actions, result.action_dim)
    np.testing.assert_array_equal(result.actions, np.asarray(ACT_OK["actions"], dtype=np.float32))
    assert result.latency_ms["denoise"] == 6.0
    assert result.request_id == "generated-1"
    assert result.model_hash == ACT_OK["model_hash"]
    assert result.inference_mode == {"backend": "cpu", "precision": "fp32", "gemm": "onednn"}
    assert result.warnings == [] and result.batch_size == 1
    assert result.raw == ACT_OK
    assert result.round_trip_ms > 0


def test_images_accept_bytes_paths_and_arrays(fake, tmp_path: Path):
    png = tiny_png()
    path = tmp_path / "frame.png"
    path.write_bytes(png)
    jpeg_like = b"\xff\xd8\xff\xe0" + b"\x00" * 16
    with fast_client(fake.url) as client:
        client.act(
            images={"front": png, "observation.images.wrist": str(path), "top": path, "side": jpeg_like},
            state=STATE,
            instruction="x",
        )
    images = fake.requests[0].json()["images"]
    assert images["front"] == png  # msgpack: file bytes as they are
    assert images["observation.images.wrist"] == images["front"] == images["top"]
    assert images["side"] == jpeg_like
    with fast_client(fake.url, body_format="json") as client:
        client.act(images={"front": png, "side": jpeg_like}, state=STATE, instruction="x")
    images = fake.requests[1].json()["images"]
    assert images["front"] == base64.b64encode(png).decode()
    assert base64.b64decode(images["side"]) == jpeg_like


def test_msgpack_answers_and_errors_are_decoded(fake):
    import msgpack

    msgpack_type = {"Content-Type": "application/msgpack"}
    error = {"error": {"code": "invalid_state", "message": "state has 2 values"}}
    fake.script = [Reply(200, msgpack.packb(ACT_OK), headers=msgpack_type),
                   Reply(400, msgpack.packb(error), headers=msgpack_type),
                   Reply(200, b"\xc1", headers=msgpack_type)]
    with fast_client(fake.url) as client:
        result = client.act(np.zeros((2, 2, 3), np.uint8), state=STATE, instruction="x")
        np.testing.assert_array_equal(result.actions, np.asarray(ACT_OK["actions"], dtype=np.float32))
        assert result.raw == ACT_OK
        with pytest.raises(InvalidRequestError) as info:
            client.act(np.zeros((2, 2, 3), np.uint8), state=STATE, instruction="x")
        assert info.value.code == "invalid_state" and info.value.body == error
        with pytest.raises(TetherError) as bad:
            client.act(np.zeros((2, 2, 3), np.uint8), state=STATE, instruction="x")
        assert bad.value.code == "bad_response"


def test_body_format_is_checked():
    with pytest.raises(ValueError, match="body_format"):
        TetherClient("http://127.0.0.1:1", body_format="xml")


def test_http_connection_sets_tcp_nodelay(fake):
    with fast_client(fake.url) as client:
        client.health()
        assert client._conn is not None and client._conn.sock is not None
        assert client._conn.sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0


def test_float_and_gray_images_are_converted():
    out = encode_image(np.array([[[0.0, 0.5, 1.0]]], dtype=np.float32))
    assert base64.b64decode(out["data"]) == bytes([0, 128, 255])
    gray = encode_image(np.array([[7, 9]], dtype=np.uint8))
    assert gray["shape"] == [1, 2, 3]
    assert base64.b64decode(gray["data"]) == bytes([7, 7, 7, 9, 9, 9])
    ints = encode_image(np.full((1, 1, 3), 200, dtype=np.int64))
    assert base64.b64decode(ints["data"]) == bytes([200] * 3)
    # A non-contiguous view is sent in row-major order.
    big = np.arange(2 * 4 * 3, dtype=np.uint8).reshape(2, 4, 3)
    view = big[:, ::2]
    assert base64.b64decode(encode_image(view)["data"]) == np.ascontiguousarray(view).tobytes()


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((3, 8, 8), dtype=np.uint8), "channels-first"),
        (np.zeros((8, 8, 4), dtype=np.uint8), "3 channels"),
        (np.zeros((8,), dtype=np.uint8), "HxWx3"),
        (np.zeros((0, 8, 3), dtype=np.uint8), "empty"),
        (np.full((2, 2, 3), 255.0, dtype=np.float32), r"\[0, 1\]"),
        (np.full((2, 2, 3), np.nan, dtype=np.float32), "NaN"),
        (np.full((2, 2, 3), 300, dtype=np.int32), r"\[0, 255\]"),
        (b"GIF89a....", "neither a PNG nor a JPEG"),
    ],
)
def test_bad_images_are_refused_before_sending(bad, match):
    with pytest.raises(ValueError, match=match):
        encode_image(bad)


def test_bad_arguments_are_refused_before_sending(fake, tmp_path):
    frame = np.zeros((2, 2, 3), np.uint8)
    with fast_client(fake.url) as client:
        with pytest.raises(ValueError, match="either image= or images="):
            client.act(frame, images={"front": frame}, state=STATE, instruction="x")
        with pytest.raises(ValueError, match="NaN or Inf"):
            client.act(frame, state=[0, float("nan"), 0, 0, 0, 0], instruction="x")
        with pytest.raises(ValueError, match="1-D"):
            client.act(frame, state=[[1, 2], [3, 4]], instruction="x")
        with pytest.raises(ValueError, match="seed"):
            client.act(frame, state=STATE, instruction="x", seed=-1)
        with pytest.raises(TypeError, match="instruction"):
            client.act(frame, state=STATE, instruction=None)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="unsupported image type"):
            client.act(object(), state=STATE, instruction="x")
        with pytest.raises(OSError):
            client.act(str(tmp_path / "missing.png"), state=STATE, instruction="x")
    assert fake.requests == []


def test_array_interface_objects_are_accepted(fake):
    class FakePicture:  # what a PIL image exposes
        def __init__(self) -> None:
            self._a = np.full((2, 3, 3), 9, dtype=np.uint8)

        @property
        def __array_interface__(self):
            return self._a.__array_interface__

    with fast_client(fake.url) as client:
        client.act(FakePicture(), state=STATE, instruction="x")
    assert fake.requests[0].json()["image"]["shape"] == [2, 3, 3]


# -- connection reuse -----------------------------------------------------------------------------------------


def test_keep_alive_reuses_one_connection_until_closed(fake):
    client = fast_client(fake.url)
    with client:
        for _ in range(3):
            client.act(state=STATE, instruction="x")
        client.health()
        client.metrics()
    ports = {r.port for r in fake.requests}
    assert len(fake.requests) == 5 and len(ports) == 1
    client.act(state=STATE, instruction="x")  # reopens after close
    assert fake.requests[-1].port not in ports
    client.close()


def test_idle_connection_closed_by_server_is_reopened_once(fake):
    fake.script = [Reply(drop=True), Reply()]
    with fast_client(fake.url) as client:
        client.act(state=STATE, instruction="first")
        time.sleep(0.1)
        result = client.act(state=STATE, instruction="second")
    assert result.actions.shape == (50, 6)
    assert [r.json()["instruction"] for r in fake.requests] == ["first", "second"]
    assert fake.requests[0].port != fake.requests[1].port


def test_early_answer_to_a_large_body_is_reported(fake):
    fake.script = [error_reply(413, "body_too_large", "request body exceeds 1024 bytes", early=True)]
    big = np.zeros((2048, 2048, 3), dtype=np.uint8)  # 12 MiB raw, far more than the socket buffers
    with fast_client(fake.url) as client:
        with pytest.raises(InvalidRequestError) as info:
            client.act(big, state=STATE, instruction="x")
    assert info.value.status == 413 and info.value.code == "body_too_large"


# -- retries --------------------------------------------------------------------------------------------------


def recorded_sleeps(monkeypatch) -> list:
    """Replaces the client's sleep with a recorder: the delays it chose are asserted, not the wall clock."""
    import tether_client.client as client_module

    delays: list = []
    monkeypatch.setattr(client_module.time, "sleep", delays.append)
    return delays


def test_503_is_retried_with_backoff_then_succeeds(fake, monkeypatch):
    fake.script = [error_reply(503, "not_ready"), error_reply(503, "queue_full"), Reply()]
    delays = recorded_sleeps(monkeypatch)
    with fast_client(fake.url, backoff=0.05, max_backoff=1.0) as client:
        result = client.act(state=STATE, instruction="x", request_id="same-id")
    assert result.actions.shape == (50, 6)
    assert len(fake.requests) == 3
    assert {r.headers["x-tether-request-id"] for r in fake.requests} == {"same-id"}
    # Two delays, doubling from the backoff, each with at most 10% jitter.
    assert len(delays) == 2
    assert 0.05 <= delays[0] <= 0.055 and 0.1 <= delays[1] <= 0.11


def test_retry_after_is_honoured(fake, monkeypatch):
    fake.script = [error_reply(503, "queue_full", headers={"Retry-After": "1"}), Reply()]
    delays = recorded_sleeps(monkeypatch)
    with fast_client(fake.url) as client:
        client.act(state=STATE, instruction="x")
    assert len(delays) == 1 and 1.0 <= delays[0] <= 1.1
    assert len(fake.requests) == 2


def test_retries_exhausted_raise_server_busy(fake):
    fake.default = error_reply(503, "queue_full", "queue is full (64 waiting)", headers={"Retry-After": "0"})
    with fast_client(fake.url, retries=3) as client:
        with pytest.raises(ServerBusyError) as info:
            client.act(state=STATE, instruction="x", request_id="rid-9")
    err = info.value
    assert len(fake.requests) == 4  # the first try and 3 retries
    assert (err.status, err.code, err.request_id, err.retry_after) == (503, "queue_full", "rid-9", 0.0)
    assert "queue is full" in err.message and "3 retries" in err.message
    assert isinstance(err, TetherError)


def test_total_retry_wait_is_bounded(fake):
    fake.default = error_reply(503, "not_ready")
    with fast_client(fake.url, retries=1000, backoff=0.1, max_backoff=0.2, max_retry_wait=0.7) as client:
        start = time.monotonic()
        with pytest.raises(ServerBusyError) as info:
            client.act(state=STATE, instruction="x")
        elapsed = time.monotonic() - start
    assert info.value.code == "not_ready"
    assert elapsed < 3.0
    assert 3 <= len(fake.requests) <= 6


def test_retries_zero_raises_at_once(fake):
    fake.default = error_reply(503, "queue_full")
    with fast_client(fake.url, retries=0) as client:
        with pytest.raises(ServerBusyError):
            client.act(state=STATE, instruction="x")
    assert len(fake.requests) == 1


def test_4xx_and_500_are_not_retried(fake):
    fake.script = [error_reply(400, "invalid_state", "state has 5 values, expected 6"), error_reply(500, "x")]
    with fast_client(fake.url) as client:
        with pytest.raises(InvalidRequestError):
            client.act(state=STATE[:5], instruction="x")
        with pytest.raises(ServerError):
            client.act(state=STATE, instruction="x")
    assert len(fake.requests) == 2


def test_health_reports_503_without_retrying(fake):
    fake.script = [Reply(503, {"status": "unavailable", "state": "warming", "model_hash": "sha256:00"})]
    with fast_client(fake.url) as client:
        health = client.health()
    assert health["state"] == "warming"
    assert len(fake.requests) == 1


def test_config_is_retried_on_503(fake):
    fake.script = [error_reply(503, "not_ready"), Reply(200, {"family": "smolvla", "state_dim": 6})]
    with fast_client(fake.url) as client:
        assert client.config()["family"] == "smolvla"
    assert [r.path for r in fake.requests] == ["/config", "/config"]


def test_wait_until_ready_polls_health(fake):
    warming = Reply(503, {"status": "unavailable", "state": "warming"})
    fake.script = [warming, warming, Reply(200, {"status": "ok", "state": "ready"})]
    with fast_client(fake.url) as client:
        assert client.wait_until_ready(timeout=5, interval=0.01)["state"] == "ready"
    fake.default = warming
    with fast_client(fake.url) as client:
        with pytest.raises(ServerBusyError, match="not ready"):
            client.wait_until_ready(timeout=0.2, interval=0.05)


# -- errors ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "status, code, cls",
    [
        (400, "invalid_state", InvalidRequestError),
        (400, "bad_json", InvalidRequestError),
        (401, "unauthorized", AuthenticationError),
        (404, "not_found", InvalidRequestError),
        (405, "method_not_allowed", InvalidRequestError),
        (408, "request_timeout", RequestTimeoutError),
        (413, "body_too_large", InvalidRequestError),
        (431, "header_too_large", InvalidRequestError),
        (500, "inference_failed", ServerError),
        (504, "deadline_exceeded", DeadlineExceededError),
    ],
)
def test_error_statuses_map_to_exceptions(fake, status, code, cls):
    fake.script = [error_reply(status, code, "what went wrong")]
    with fast_client(fake.url) as client:
        with pytest.raises(cls) as info:
            client.act(state=STATE, instruction="x", request_id="req-42")
    err = info.value
    assert (err.status, err.code, err.message, err.request_id) == (status, code, "what went wrong", "req-42")
    assert err.body == {"error": {"code": code, "message": "what went wrong"}}
    assert str(status) in str(err) and code in str(err) and "req-42" in str(err)


def test_non_json_error_body(fake):
    fake.script = [Reply(502, "upstream proxy error")]
    with fast_client(fake.url) as client:
        with pytest.raises(ServerError) as info:
            client.act(state=STATE, instruction="x")
    assert info.value.code == "http_502" and info.value.message == "upstream proxy error"


def test_malformed_success_body(fake):
    fake.script = [Reply(200, {**ACT_OK, "num_actions": 49})]
    with fast_client(fake.url) as client:
        with pytest.raises(TetherError, match="shape") as info:
            client.act(state=STATE, instruction="x")
    assert info.value.code == "bad_response"


def test_connection_refused():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again: nothing listens there
    with fast_client(f"http://127.0.0.1:{port}") as client:
        with pytest.raises(TetherConnectionError) as info:
            client.act(state=STATE, instruction="x")
    assert info.value.status is None and info.value.code == "connection_error"


def test_socket_timeout(fake):
    fake.script = [Reply(delay=1.0)]
    with fast_client(fake.url, timeout=0.2) as client:
        start = time.monotonic()
        with pytest.raises(TetherTimeoutError) as info:
            client.act(state=STATE, instruction="x")
        assert time.monotonic() - start < 3.0
    assert isinstance(info.value, TetherConnectionError) and info.value.code == "timeout"


# -- headers, auth, episodes ----------------------------------------------------------------------------------


def test_api_key_from_argument_env_or_none(fake, monkeypatch):
    monkeypatch.setenv("TETHER_API_KEY", "from-env")
    with TetherClient(fake.url, api_key="explicit") as client:
        client.config()
    with TetherClient(fake.url) as client:
        client.config()
    with TetherClient(fake.url, api_key="") as client:
        client.config()
    auth = [r.headers.get("authorization") for r in fake.requests]
    assert auth == ["Bearer explicit", "Bearer from-env", None]


def test_request_id_header_is_sent(fake):
    with fast_client(fake.url) as client:
        client.act(state=STATE, instruction="x", request_id="abc.DEF:1-2_3")
        client.act(state=STATE, instruction="x")
    assert fake.requests[0].headers["x-tether-request-id"] == "abc.DEF:1-2_3"
    assert "x-tether-request-id" not in fake.requests[1].headers


def test_episode_sets_one_fresh_id_per_block(fake):
    with fast_client(fake.url) as client:
        client.act(state=STATE, instruction="before")
        with client.episode() as ep1:
            assert client.episode_id == ep1.episode_id
            client.act(state=STATE, instruction="a")
            ep1.act(state=STATE, instruction="b")
            client.act(state=STATE, instruction="override", episode_id="explicit")
            with client.episode("inner") as inner:
                client.act(state=STATE, instruction="nested")
            client.act(state=STATE, instruction="after nested")
        with client.episode() as ep2:
            client.act(state=STATE, instruction="c")
        client.act(state=STATE, instruction="after")
    ids = [r.json().get("episode_id") for r in fake.requests]
    assert ids == [None, ep1.episode_id, ep1.episode_id, "explicit", "inner", ep1.episode_id, ep2.episode_id, None]
    assert inner.episode_id == "inner"
    assert ep1.episode_id != ep2.episode_id
    assert uuid.UUID(ep1.episode_id).version == 4 and uuid.UUID(ep2.episode_id).version == 4


def test_episode_is_per_thread(fake):
    client = fast_client(fake.url)
    seen = {}

    def other_thread():
        client.act(state=STATE, instruction="thread")

    with client.episode() as ep:
        t = threading.Thread(target=other_thread)
        t.start()
        t.join()
        client.act(state=STATE, instruction="main")
    client.close()
    for r in fake.requests:
        seen[r.json()["instruction"]] = r.json().get("episode_id")
    assert seen == {"thread": None, "main": ep.episode_id}


def test_concurrent_calls_share_the_client_safely(fake):
    errors = []
    with fast_client(fake.url) as client:

        def worker():
            try:
                for _ in range(5):
                    assert client.act(state=STATE, instruction="x").actions.shape == (50, 6)
            except Exception as e:  # pragma: no cover - reported below
                errors.append(e)

        threads = [threading.Thread(target=worker) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert errors == [] and len(fake.requests) == 20


def test_metrics_returns_text_and_alias(fake):
    fake.script = [Reply(200, b"# TYPE tether_model_ready gauge\ntether_model_ready 1\n")]
    with ReflexClient(fake.url, api_key="") as client:
        assert "tether_model_ready 1" in client.metrics()
    assert ReflexClient is TetherClient


def test_url_forms(fake):
    with TetherClient(f"127.0.0.1:{fake.port}", api_key="") as client:
        client.health()
    with TetherClient(fake.url + "/prefix/", api_key="") as client:
        client.health()
    assert [r.path for r in fake.requests] == ["/health", "/prefix/health"]
    with pytest.raises(ValueError, match="scheme"):
        TetherClient("ftp://host")


def test_non_object_json_answer_is_reported(fake):
    fake.script = [Reply(200, [1, 2]), Reply(200, "<html>proxy page</html>")]
    with fast_client(fake.url) as client:
        for _ in range(2):
            with pytest.raises(TetherError) as info:
                client.health()
            assert info.value.code == "bad_response" and info.value.status == 200


# -- safety wedges --------------------------------------------------------------------------------------------


def test_rtc_fields_are_sent_and_wedge_fields_parsed(fake):
    body = dict(ACT_OK, action_source="last_good", deadline_exceeded=True, guard_clamped=True,
                guard_violations=[{"step": 0, "joint": "gripper", "limit": "velocity", "value": 9.0, "applied": 1.0}])
    fake.script = [Reply(200, body)]
    with fast_client(fake.url) as client:
        result = client.act(state=STATE, instruction="x", prev_actions=np.zeros((3, 6)), inference_delay=2)
    assert fake.requests[0].json()["rtc"] == {"prev_actions": [[0.0] * 6] * 3, "inference_delay": 2}
    assert result.deadline_exceeded and result.guard_clamped and result.action_source == "last_good"
    assert result.wedges["guard_violations"][0]["joint"] == "gripper"
    assert "actions" not in result.wedges and "latency_ms" not in result.wedges


def test_rtc_arguments_are_checked_before_sending(fake):
    with fast_client(fake.url) as client:
        with pytest.raises(ValueError):
            client.act(state=STATE, instruction="x", prev_actions=[1.0, 2.0])
        with pytest.raises(ValueError):
            client.act(state=STATE, instruction="x", inference_delay=2)
        with pytest.raises(ValueError):
            client.act(state=STATE, instruction="x", prev_actions=[[float("nan")] * 6])
    assert fake.requests == []


def test_open_circuit_is_not_waited_out(fake):
    fake.default = error_reply(503, "circuit_open", "open", headers={"Retry-After": "60"})
    with fast_client(fake.url, max_retry_wait=5) as client:
        start = time.monotonic()
        with pytest.raises(CircuitOpenError) as info:
            client.act(state=STATE, instruction="x")
    assert time.monotonic() - start < 2 and info.value.retry_after == 60
    assert isinstance(info.value, ServerBusyError)
