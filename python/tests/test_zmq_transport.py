"""Tether's own ZMQ transport (`tether serve --zmq-port`) through the real binary: msgpack requests with /act's fields
over DEALER and REQ sockets (zmq_clients.py), request ids matched by `id`, errors and framing garbage, limits, CURVE
encryption, host names for --host (both ZMQ transports), the API key, metrics, traces, the safety wedges, and
TetherClient(transport="zmq")."""

from __future__ import annotations

import subprocess
import time
from typing import Any, Dict

import numpy as np
import pytest

msgpack = pytest.importorskip("msgpack")
zmq = pytest.importorskip("zmq")

from serve_process import DEMO, binary_path, metric  # noqa: E402
from test_serve_integration import STATE, act_body, check_actions, ok_json, post_act  # noqa: E402
from tether_client import AuthenticationError, InvalidRequestError, TetherClient  # noqa: E402
from zmq_clients import PNG, Dealer, Gr00tClient, act_msg, connect, metrics_of, served, trace_lines  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

CHUNK, DIM = 50, 6


@pytest.fixture(scope="module")
def zserver():
    with served(["--zmq-port", "0"]) as proc:
        yield proc


@pytest.fixture
def dealer(zserver):
    with Dealer(zserver.transport_ports["zmq"]) as d:
        yield d


def test_act_matches_http_and_echoes_id(zserver, dealer):
    assert any(line.startswith("tether serve: zmq listening on 127.0.0.1:") for line in zserver.stdout_seen)
    reply = dealer.act(id="abc", request_id="robot-1.step-3")
    assert reply["status"] == 200 and reply["id"] == "abc" and reply["request_id"] == "robot-1.step-3"
    actions = np.asarray(reply["actions"], np.float32)
    assert actions.shape == (CHUNK, DIM) and reply["num_actions"] == CHUNK and reply["action_dim"] == DIM
    np.testing.assert_allclose(actions, check_actions(ok_json(post_act(zserver, act_body(seed=7)))), rtol=0, atol=1e-5)


def test_raw_image_and_pipelined_requests_match_by_id(dealer):
    raw = {"data": bytes(range(256)) * 3, "shape": [16, 16, 3]}
    for i in range(4):
        dealer.send(act_msg(image=None, images={"front": raw}, seed=i, id=i))
    replies = [dealer.recv() for _ in range(4)]
    assert sorted(r["id"] for r in replies) == [0, 1, 2, 3]
    assert all(r["status"] == 200 for r in replies)


def test_req_socket_and_errors(zserver):
    req = connect(zmq.REQ, zserver.transport_ports["zmq"])
    try:
        def ask(raw: bytes) -> Dict[str, Any]:
            req.send(raw)
            return msgpack.unpackb(req.recv())

        for raw, status, code in [
            (b"\xc1\x00", 400, "bad_msgpack"),
            (msgpack.packb([1, 2]), 400, "bad_msgpack"),
            (msgpack.packb(act_msg(state=[1.0])), 400, "invalid_state"),
            (msgpack.packb(act_msg(colour="red")), 400, "unknown_field"),
            (msgpack.packb(act_msg(image=b"\x89PNG\r\n\x1a\nbroken")), 400, "invalid_image"),
            (msgpack.packb(act_msg(image=None, images={"top": PNG})), 400, "unknown_camera"),
        ]:
            reply = ask(raw)
            assert reply["status"] == status and reply["error"]["code"] == code, reply
        assert ask(msgpack.packb(act_msg()))["status"] == 200
    finally:
        req.close(0)


def test_multipart_garbage(zserver, dealer):
    dealer.socket.send_multipart([b"one", b"two"])
    assert dealer.recv()["error"]["code"] == "bad_frames"
    dealer.socket.send_multipart([b"", b""])
    assert dealer.recv()["error"]["code"] == "bad_frames"
    assert dealer.act()["status"] == 200


def test_limits():
    with served(["--zmq-port", "0", "--zmq-max-message-bytes", "100000", "--max-body-bytes", "20000"]) as proc:
        port = proc.transport_ports["zmq"]
        with Dealer(port, timeout_ms=1500) as d:
            d.send(act_msg(pad=b"x" * 200000))  # above ZMQ_MAXMSGSIZE: libzmq drops the peer, no answer
            with pytest.raises(zmq.Again):
                d.recv()
        with Dealer(port) as d:
            reply = d.act(image=None, images={"front": {"data": b"\x80" * (100 * 100 * 3), "shape": [100, 100, 3]}})
            assert reply["status"] == 413 and reply["error"]["code"] == "body_too_large"
            assert d.act(image={"data": b"\x80" * 12, "shape": [2, 2, 3]})["status"] == 200


def test_curve_encryption(tmp_path):
    public, secret = zmq.curve_keypair()
    key_file = tmp_path / "server.key"
    key_file.write_bytes(secret + b"\n")
    with served(["--zmq-port", "0", "--zmq-curve-secret-file", str(key_file)]) as proc:
        assert f"zmq CURVE public key {public.decode()}" in proc.stderr_tail()
        port = proc.transport_ports["zmq"]
        with Dealer(port, server_key=public) as d:
            assert d.act()["status"] == 200
        with Dealer(port, timeout_ms=1500) as plain:  # without CURVE: the handshake fails, nothing is answered
            plain.send(act_msg())
            with pytest.raises(zmq.Again):
                plain.recv()
        with TetherClient(proc.url, transport="zmq", zmq_url=f"tcp://127.0.0.1:{port}",
                          zmq_server_key=public.decode()) as client:
            assert client.act(PNG, state=STATE, instruction="pick", seed=1).actions.shape == (CHUNK, DIM)


def start_failure(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary_path()), "serve", str(DEMO), "--port", "0", *args], capture_output=True,
                          text=True, timeout=60)


def test_bad_curve_key_fails_at_start(tmp_path):
    bad = tmp_path / "bad.key"
    bad.write_text("not-a-key")
    proc = start_failure("--zmq-port", "0", "--zmq-curve-secret-file", str(bad))
    assert proc.returncode != 0 and "CURVE" in proc.stderr


def test_host_name_is_resolved_for_both_zmq_transports():
    # libzmq binds numeric addresses only: the server resolves the name and binds each of its addresses.
    with served(["--host", "localhost", "--zmq-port", "0", "--gr00t-port", "0"]) as proc:
        for name in ("zmq", "gr00t"):
            assert any(line.startswith(f"tether serve: {name} listening on localhost:") for line in proc.stdout_seen)
        with Dealer(proc.transport_ports["zmq"], host="localhost") as d:
            assert d.act()["status"] == 200
        with Gr00tClient(proc.transport_ports["gr00t"], host="127.0.0.1") as c:
            assert c.call("ping", requires_input=False)["status"] == "ok"


def test_unresolvable_host_is_a_usage_error():
    proc = start_failure("--host", "no-such-host.invalid", "--zmq-port", "0", "--gr00t-port", "0")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "no-such-host.invalid" in lines[0], proc.stderr


def test_api_key_client_and_metrics():
    with served(["--zmq-port", "0"], env={"TETHER_API_KEY": "sesame"}) as proc:
        port = proc.transport_ports["zmq"]
        with Dealer(port) as d:
            assert d.act()["error"]["code"] == "unauthorized"
            assert d.act(api_key="sesame")["status"] == 200
        url = f"tcp://127.0.0.1:{port}"
        with TetherClient(proc.url, api_key="sesame", transport="zmq", zmq_url=url) as client:
            result = client.act(PNG, state=STATE, instruction="pick", seed=7, request_id="zmq-client-1")
            assert result.actions.shape == (CHUNK, DIM) and result.actions.dtype == np.float32
            assert result.request_id == "zmq-client-1" and result.action_source == "model"
            with pytest.raises(InvalidRequestError) as e:
                client.act(PNG, state=[1.0], instruction="pick")
            assert e.value.code == "invalid_state"
            assert client.config()["state_dim"] == 6  # everything but act stays on HTTP
        with TetherClient(proc.url, api_key="wrong", transport="zmq", zmq_url=url) as client:
            with pytest.raises(AuthenticationError):
                client.act(np.zeros((8, 8, 3), np.uint8), state=STATE, instruction="pick")
        m = metrics_of(proc)
        assert metric(m, "tether_requests_total", transport="zmq", endpoint="/act", status="200") == 2
        assert metric(m, "tether_requests_total", transport="zmq", status="401") == 2
        assert metric(m, "tether_requests_total", transport="zmq", status="400") == 1


def test_guard_traces_deadline_breaker(tmp_path):
    record = tmp_path / "traces"
    with served(["--zmq-port", "0", "--embodiment", "so100", "--record", str(record)]) as proc, \
            Dealer(proc.transport_ports["zmq"]) as d:
        reply = d.act(episode_id="z1")
        a = np.asarray(reply["actions"])
        assert np.all(a[:, :5] >= -100) and np.all(a[:, :5] <= 100) and np.all(a[:, 5] >= 0) and np.all(a[:, 5] <= 100)
        assert "guard_clamped" in reply and reply["joint_names"][0] == "shoulder_pan"
        assert d.act(state=[0.0])["status"] == 400
        d.socket.send(b"\xc1")  # not msgpack: refused while decoding, traced too
        assert d.recv()["error"]["code"] == "bad_msgpack"
        assert metric(metrics_of(proc), "tether_requests_total", transport="zmq", status="400") == 2
    lines = trace_lines(record)
    assert len(lines) == 3 and all(line["transport"] == "zmq" for line in lines)
    assert lines[0]["episode_id"] == "z1"
    assert lines[2]["status"] == "failed" and lines[2]["error"]["code"] == "bad_msgpack"

    with served(["--zmq-port", "0", "--inject-latency-ms", "600", "--deadline-ms", "150",
                 "--request-timeout-ms", "5000"]) as proc, Dealer(proc.transport_ports["zmq"]) as d:
        first = d.act(episode_id="slow")
        assert first["status"] == 504 and first["error"]["code"] == "deadline_exceeded"
        for _ in range(120):
            reply = d.act(episode_id="slow")
            if reply["status"] == 200:
                break
            time.sleep(0.5)
        else:
            raise AssertionError("the late forward pass never became the last good chunk")
        assert reply["deadline_exceeded"] is True and reply["action_source"] == "last_good"

    fault = tmp_path / "fail-now"
    with served(["--zmq-port", "0", "--max-consecutive-crashes", "2", "--inject-failure-file", str(fault)]) as proc, \
            Dealer(proc.transport_ports["zmq"]) as d:
        fault.touch()
        for _ in range(2):
            assert d.act()["error"]["code"] == "inference_failed"
        reply = d.act()
        assert reply["status"] == 503 and reply["error"]["code"] == "circuit_open" and reply["retry_after_s"] >= 1
        assert metric(metrics_of(proc), "tether_requests_total", transport="zmq", status="503") == 1
