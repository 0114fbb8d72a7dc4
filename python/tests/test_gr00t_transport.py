"""The GR00T ZMQ transport (`tether serve --gr00t-port`) through the real binary, spoken to by a client written from
Isaac-GR00T's PolicyClient protocol (a REQ socket, msgpack requests {endpoint, data, api_token}, numpy arrays as
{"__ndarray_class__": True, "as_npy": <.npy bytes>}, zmq_clients.py): endpoints, both observation layouts, batches,
errors, framing garbage, the API token, reset ending an episode, metrics, traces and the safety wedges."""

from __future__ import annotations

import base64
import time
from typing import Any, Dict, Optional

import numpy as np
import pytest

msgpack = pytest.importorskip("msgpack")
zmq = pytest.importorskip("zmq")

from serve_process import ServeProcess, binary_path, metric  # noqa: E402
from test_serve_integration import STATE, act_body, check_actions, ok_json, post_act  # noqa: E402
from zmq_clients import Gr00tClient, connect, metrics_of, pack, served, trace_lines, unpack  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

CHUNK, DIM = 50, 6
FRAME = (np.arange(16 * 16 * 3) % 251).astype(np.uint8).reshape(16, 16, 3)


def nested_obs(batch: int = 1, frames: int = 1, camera: str = "front", state_dim: int = 6) -> Dict[str, Any]:
    video = np.broadcast_to(FRAME, (batch, frames) + FRAME.shape).copy()
    state = np.broadcast_to(np.asarray(STATE[:state_dim] + [0.0] * max(0, state_dim - 6), np.float32),
                            (batch, frames, state_dim)).copy()
    return {"video": {camera: video}, "state": {"state": state},
            "language": {"task": [["pick up the red cube"]] * batch}}


def http_actions(server: ServeProcess, seed: int) -> np.ndarray:
    image = {"data": base64.b64encode(FRAME.tobytes()).decode(), "shape": list(FRAME.shape)}
    return check_actions(ok_json(post_act(server, act_body(image=image, seed=seed))))


@pytest.fixture(scope="module")
def gserver():
    with served(["--gr00t-port", "0"]) as proc:
        yield proc


@pytest.fixture
def client(gserver):
    with Gr00tClient(gserver.transport_ports["gr00t"]) as c:
        yield c


# -- endpoints -------------------------------------------------------------------------------------------------


def test_listening_line_and_ping_reset(gserver, client):
    assert any(line.startswith("tether serve: gr00t listening on 127.0.0.1:") for line in gserver.stdout_seen)
    assert client.call("ping", requires_input=False) == {"status": "ok", "message": "Server is running"}
    assert client.call("reset", {"options": None}) == {}


def test_modality_config_describes_the_checkpoint(client):
    cfg = client.call("get_modality_config", requires_input=False)
    assert cfg["video"]["modality_keys"] == ["front"] and cfg["video"]["delta_indices"] == [0]
    assert cfg["state"]["modality_keys"] == ["state"]
    assert cfg["action"]["modality_keys"] == ["action"] and cfg["action"]["delta_indices"] == list(range(CHUNK))
    assert cfg["language"]["modality_keys"] == ["task"]
    assert set(cfg["video"]) == {"delta_indices", "modality_keys", "sin_cos_embedding_keys", "mean_std_embedding_keys",
                                 "action_configs"}
    assert cfg["tether"]["state_dim"] == 6 and cfg["tether"]["action_dim"] == DIM
    # A lerobot checkpoint: one state group and one action group, named after its features.
    assert cfg["tether"]["state_groups"] == [{"name": "state", "dim": 6}]
    assert cfg["tether"]["action_groups"] == [{"name": "action", "dim": DIM}]
    assert cfg["tether"]["camera_keys"] == ["observation.images.front"]


def test_get_action_nested_matches_http(gserver, client):
    reply = client.get_action(nested_obs(), {"seed": 7})
    assert isinstance(reply, list) and len(reply) == 2
    actions, info = reply
    assert set(actions) == {"action"}
    a = actions["action"]
    assert a.dtype == np.float32 and a.shape == (1, CHUNK, DIM)
    np.testing.assert_allclose(a[0], http_actions(gserver, 7), rtol=0, atol=1e-5)
    item = info["tether"][0]
    assert item["num_actions"] == CHUNK and item["action_source"] == "model" and item["request_id"]


def test_get_action_flat_batch_with_history(gserver, client):
    obs = nested_obs(batch=2, frames=3)
    # An older frame differs: only the last one of the history is used.
    obs["video"]["front"][:, 0] = 0
    flat = {"video.front": obs["video"]["front"], "state.state": obs["state"]["state"],
            "task": ["pick up the red cube"] * 2}
    actions, info = client.get_action(flat, {"seed": [7, 8]})
    a = actions["action.action"]
    assert a.shape == (2, CHUNK, DIM) and a.dtype == np.float32
    np.testing.assert_allclose(a[0], http_actions(gserver, 7), rtol=0, atol=1e-5)
    np.testing.assert_allclose(a[1], http_actions(gserver, 8), rtol=0, atol=1e-5)
    assert len(info["tether"]) == 2


def test_concurrent_clients_batch_together(gserver):
    clients = [Gr00tClient(gserver.transport_ports["gr00t"]) for _ in range(4)]
    try:
        for i, c in enumerate(clients):
            c.socket.send(pack({"endpoint": "get_action", "data": {"observation": nested_obs(), "options": {"seed": i}}}))
        replies = [unpack(c.socket.recv()) for c in clients]
    finally:
        for c in clients:
            c.close()
    assert all(r[0]["action"].shape == (1, CHUNK, DIM) for r in replies)
    assert max(r[1]["tether"][0]["batch_size"] for r in replies) >= 1


# -- errors ----------------------------------------------------------------------------------------------------


def test_errors_are_answered_and_serving_goes_on(client):
    err = client.get_action(nested_obs(camera="top"))
    assert err["code"] == "unknown_camera" and "top" in err["error"] and err["status"] == 400
    err = client.get_action(nested_obs(state_dim=4))
    assert err["code"] == "invalid_state"
    err = client.call("explode", {})
    assert err["error"] == "Unknown endpoint: explode"
    err = client.call("kill", requires_input=False)
    assert err["code"] == "kill_disabled"
    obs = nested_obs()
    obs["video"]["front"] = obs["video"]["front"].astype(np.float32)
    assert client.get_action(obs)["code"] == "invalid_field"
    # Malformed msgpack, and a map that is not a request.
    client.socket.send(b"\xc1\xff")
    assert unpack(client.socket.recv())["code"] == "bad_msgpack"
    client.socket.send(msgpack.packb([1, 2]))
    assert unpack(client.socket.recv())["code"] == "bad_msgpack"
    assert client.call("ping", requires_input=False)["status"] == "ok"


def test_multipart_garbage_is_answered_or_dropped(gserver):
    port = gserver.transport_ports["gr00t"]
    dealer = connect(zmq.DEALER, port, timeout_ms=10000)
    try:
        dealer.send_multipart([b"", b"a", b"b"])  # two message frames
        reply = dealer.recv_multipart()
        assert reply[0] == b"" and unpack(reply[-1])["code"] == "bad_frames"
        dealer.send_multipart([b"", b""])  # an empty message frame
        assert unpack(dealer.recv_multipart()[-1])["code"] == "bad_frames"
        dealer.send_multipart([pack({"endpoint": "ping"})])  # no delimiter: answered without one
        reply = dealer.recv_multipart()
        assert len(reply) == 1 and unpack(reply[0])["status"] == "ok"
    finally:
        dealer.close(0)
    with Gr00tClient(port) as c:
        assert c.call("ping", requires_input=False)["status"] == "ok"


def test_oversize_message_is_dropped(tmp_path):
    with served(["--gr00t-port", "0", "--gr00t-max-message-bytes", "4096"]) as proc:
        port = proc.transport_ports["gr00t"]
        with Gr00tClient(port, timeout_ms=1500) as big:
            big.socket.send(pack({"endpoint": "ping", "data": {"pad": b"x" * 10000}}))
            with pytest.raises(zmq.Again):
                big.socket.recv()
        with Gr00tClient(port) as c:
            assert c.call("ping", requires_input=False)["status"] == "ok"


def test_api_token(tmp_path):
    with served(["--gr00t-port", "0"], env={"TETHER_API_KEY": "sesame"}) as proc:
        port = proc.transport_ports["gr00t"]
        with Gr00tClient(port) as anon:
            err = anon.call("ping", requires_input=False)
            assert err["error"].startswith("Unauthorized: Invalid API token") and err["status"] == 401
            assert anon.get_action(nested_obs())["code"] == "unauthorized"
        with Gr00tClient(port, api_token="sesame") as good:
            assert good.call("ping", requires_input=False)["status"] == "ok"
            assert good.get_action(nested_obs())[0]["action"].shape == (1, CHUNK, DIM)
        m = metrics_of(proc)
        assert metric(m, "tether_requests_total", transport="gr00t", status="401") == 1
        assert metric(m, "tether_requests_total", transport="gr00t", status="200") == 1


def test_kill_shuts_down_gracefully_when_allowed():
    proc = ServeProcess(["--gr00t-port", "0", "--gr00t-allow-kill"])
    c = Gr00tClient(proc.transport_ports["gr00t"])
    try:
        assert c.call("kill", requires_input=False) is None
        assert proc.proc.wait(timeout=30) == 0
    finally:
        c.close()
        proc.kill()


# -- wedges, traces, metrics -----------------------------------------------------------------------------------


def test_guard_and_traces_and_metrics(tmp_path):
    record = tmp_path / "traces"
    with served(["--gr00t-port", "0", "--embodiment", "so100", "--record", str(record)]) as proc, \
            Gr00tClient(proc.transport_ports["gr00t"]) as c:
        actions, info = c.get_action(nested_obs(), {"episode_id": "g1"})
        a = actions["action"][0]
        assert np.all(a[:, :5] >= -100) and np.all(a[:, :5] <= 100) and np.all(a[:, 5] >= 0) and np.all(a[:, 5] <= 100)
        assert "guard_clamped" in info["tether"][0]
        assert c.get_action(nested_obs(state_dim=3))["code"] == "invalid_state"
        c.socket.send(b"\xc1\xff")  # not msgpack: refused while decoding, counted and traced too
        garbage = unpack(c.socket.recv())
        assert garbage["code"] == "bad_msgpack" and garbage["status"] == 400
        m = metrics_of(proc)
        assert metric(m, "tether_requests_total", transport="gr00t", endpoint="/act", status="200") == 1
        assert metric(m, "tether_requests_total", transport="gr00t", status="400") == 2
    lines = trace_lines(record)
    assert len(lines) == 3
    assert all(line["transport"] == "gr00t" for line in lines)
    assert lines[0]["episode_id"] == "g1" and lines[0]["status"] == "success"
    assert lines[1]["status"] == "failed"
    assert lines[2]["status"] == "failed" and lines[2]["error"]["code"] == "bad_msgpack"


def test_deadline_answers_from_the_last_good_chunk():
    with served(["--gr00t-port", "0", "--inject-latency-ms", "600", "--deadline-ms", "150",
                 "--request-timeout-ms", "5000"]) as proc, Gr00tClient(proc.transport_ports["gr00t"]) as c:
        first = c.get_action(nested_obs(), {"seed": 7, "episode_id": "slow"})
        assert first["code"] == "deadline_exceeded" and first["status"] == 504
        for _ in range(120):
            reply = c.get_action(nested_obs(), {"seed": 7, "episode_id": "slow"})
            if isinstance(reply, list):
                break
            assert reply["code"] == "deadline_exceeded"
            time.sleep(0.5)
        else:
            raise AssertionError("the late forward pass never became the last good chunk")
        item = reply[1]["tether"][0]
        assert item["deadline_exceeded"] is True and item["action_source"] == "last_good"
        assert reply[0]["action"].shape == (1, CHUNK, DIM)


def test_reset_ends_the_episode():
    # With the similarity skip on, a repeated observation is answered from the episode's cached chunk; after reset the
    # episode starts from nothing, so the model runs again.
    with served(["--gr00t-port", "0", "--action-similarity-threshold", "0.01", "--max-similar-skips", "5"]) as proc, \
            Gr00tClient(proc.transport_ports["gr00t"]) as c:

        def source(episode: Optional[str]) -> str:
            options = {"seed": 7} if episode is None else {"seed": 7, "episode_id": episode}
            return c.get_action(nested_obs(), options)[1]["tether"][0]["action_source"]

        assert [source("r1"), source("r1"), source("r2")] == ["model", "cache", "model"]
        assert c.call("reset", {"options": {"episode_id": "r1"}}) == {}
        assert source("r1") == "model" and source("r2") == "cache"  # only the named episode ended
        assert c.call("reset", {"options": {"episode_id": ["r1", "r2"]}}) == {}
        assert source("r1") == "model" and source("r2") == "model"
        # Without an episode_id, reset ends the default episode, the one get_action without one uses.
        assert [source(None), source(None)] == ["model", "cache"]
        assert c.call("reset", {"options": None}) == {}
        assert source(None) == "model" and source("r1") == "cache"
        err = c.call("reset", {"options": {"episode_id": 5}})
        assert err["code"] == "invalid_field" and "episode_id" in err["error"]


def test_breaker_opens(tmp_path):
    fault = tmp_path / "fail-now"
    with served(["--gr00t-port", "0", "--max-consecutive-crashes", "2", "--inject-failure-file", str(fault)]) as proc, \
            Gr00tClient(proc.transport_ports["gr00t"]) as c:
        fault.touch()  # after the warm-up
        for _ in range(2):
            assert c.get_action(nested_obs())["code"] == "inference_failed"
        err = c.get_action(nested_obs())
        assert err["code"] == "circuit_open" and err["status"] == 503
        assert metric(metrics_of(proc), "tether_requests_total", transport="gr00t", status="503") == 1
