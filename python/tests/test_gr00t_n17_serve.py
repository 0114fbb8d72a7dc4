"""A GR00T N1.7 checkpoint (the oracle fixture `tests/fixtures/gr00t_n17/cam2_new`) served by the real binary with
`--embodiment-tag`: the GR00T ZMQ transport reports the embodiment's modality config (its cameras and its state and
action groups, as the checkpoint's processor_config.json names them), answers get_action per action group, and agrees
with HTTP /act on the same seed; an observation missing a group or a camera is a clear error. openpi_client, Tether ZMQ
and tritonclient get the same chunk as /act, and `tether go --model gr00t-n1.7` pulls, exports one embodiment and
serves it; the action guard, adaptive steps, the deadline and traces act on a GR00T chunk."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

msgpack = pytest.importorskip("msgpack")
zmq = pytest.importorskip("zmq")

from pngutil import decode_png_rgb8  # noqa: E402
from serve_process import REPO, ServeProcess, binary_path, request  # noqa: E402
from zmq_clients import Gr00tClient  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

CASE = REPO / "tests" / "fixtures" / "gr00t_n17" / "cam2_new"
HUB = REPO / "tests" / "fixtures" / "gr00t_hub"
STATE = {"arm": [0.1, 0.2, 0.3, 0.1, 0.2, 0.3], "gripper": [0.5], "base": [0.1, 0.2]}
TASK = "pick up the red cube and place it in the bowl"
CHUNK = 6  # the checkpoint's action steps (action.delta_indices), of the model's 8-row horizon


def frames():
    return {cam: decode_png_rgb8((CASE / "inputs" / f"{cam}.png").read_bytes()) for cam in ("front", "wrist")}


@pytest.fixture(scope="module")
def server():
    proc = ServeProcess(["--gr00t-port", "0", "--embodiment-tag", "new_embodiment"], env={"HF_HUB_CACHE": str(HUB)},
                        checkpoint=CASE / "checkpoint")
    try:
        yield proc
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


@pytest.fixture
def client(server):
    with Gr00tClient(server.transport_ports["gr00t"]) as c:
        yield c


def nested_obs():
    return {"video": {cam: img[None, None] for cam, img in frames().items()},
            "state": {k: np.asarray(v, np.float32)[None, None] for k, v in STATE.items()},
            "language": {"task": [[TASK]]}}


def test_modality_config_is_the_embodiments(client):
    cfg = client.call("get_modality_config", requires_input=False)
    assert cfg["video"]["modality_keys"] == ["front", "wrist"]
    assert cfg["state"]["modality_keys"] == ["arm", "gripper", "base"]
    assert cfg["action"]["modality_keys"] == ["arm", "gripper"]
    assert cfg["action"]["delta_indices"] == list(range(CHUNK))
    assert cfg["tether"]["state_groups"] == [{"name": "arm", "dim": 6}, {"name": "gripper", "dim": 1},
                                             {"name": "base", "dim": 2}]


def test_get_action_per_group_matches_http(server, client):
    actions, info = client.get_action(nested_obs(), {"seed": 11})
    assert set(actions) == {"arm", "gripper"}
    assert actions["arm"].shape == (1, CHUNK, 6) and actions["gripper"].shape == (1, CHUNK, 1)
    images = {cam: {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}
              for cam, img in frames().items()}
    body = json.dumps({"instruction": TASK, "state": STATE["arm"] + STATE["gripper"] + STATE["base"],
                       "images": images, "seed": 11}).encode()
    status, _, raw = request(server.port, "POST", "/act", body, {"Content-Type": "application/json"})
    assert status == 200, raw[:300]
    http = np.asarray(json.loads(raw)["actions"], np.float32)
    assert http.shape == (CHUNK, 7)
    np.testing.assert_allclose(np.concatenate([actions["arm"][0], actions["gripper"][0]], axis=1), http, rtol=0,
                               atol=1e-5)


def test_missing_group_or_camera_is_a_clear_error(client):
    obs = nested_obs()
    del obs["state"]["base"]
    err = client.get_action(obs)
    assert err["status"] == 400 and "base" in err["error"], err
    obs = nested_obs()
    del obs["video"]["wrist"]
    err = client.get_action(obs)
    assert err["status"] == 400 and "wrist" in err["error"], err
    assert client.call("ping", requires_input=False)["status"] == "ok"


# -- every transport on a GR00T checkpoint ------------------------------------------------------------------------

def http_act(port: int, seed: int) -> np.ndarray:
    images = {cam: {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}
              for cam, img in frames().items()}
    body = json.dumps({"instruction": TASK, "state": STATE["arm"] + STATE["gripper"] + STATE["base"],
                       "images": images, "seed": seed}).encode()
    status, _, raw = request(port, "POST", "/act", body, {"Content-Type": "application/json"})
    assert status == 200, raw[:300]
    return np.asarray(json.loads(raw)["actions"], np.float32)


@pytest.fixture(scope="module")
def all_transports(tmp_path_factory):
    layout = tmp_path_factory.mktemp("openpi") / "gr00t_layout.json"
    layout.write_text(json.dumps({"images": {"cams/front": "front", "cams/wrist": "wrist"},
                                  "state": ["robot/arm", "robot/gripper", "robot/base"], "prompt": "task"}))
    proc = ServeProcess(["--embodiment-tag", "new_embodiment", "--openpi-port", "0", "--openpi-layout", str(layout),
                         "--zmq-port", "0", "--model-name", "gr00t", "--rtc"], env={"HF_HUB_CACHE": str(HUB)},
                        checkpoint=CASE / "checkpoint")
    try:
        yield proc
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# openpi_client 0.1.2 keeps the connection outside a `with` block, which websockets 14+ warns about.
@pytest.mark.filterwarnings("ignore:connect\\(\\) must be used as a context manager:DeprecationWarning")
def test_openpi_zmq_and_kserve_answer_as_http(all_transports):
    """The same observation and seed through openpi_client, Tether ZMQ and tritonclient give /act's chunk."""
    want = http_act(all_transports.port, 5)
    assert want.shape == (CHUNK, 7)

    websocket_client_policy = pytest.importorskip("openpi_client.websocket_client_policy")
    policy = websocket_client_policy.WebsocketClientPolicy("127.0.0.1", all_transports.transport_ports["openpi"])
    obs = {"cams/front": frames()["front"], "cams/wrist": frames()["wrist"],
           "robot/arm": np.asarray(STATE["arm"]), "robot/gripper": np.asarray(STATE["gripper"]),
           "robot/base": np.asarray(STATE["base"]), "task": TASK, "seed": 5}
    got = np.asarray(policy.infer(obs)["actions"], np.float32)
    np.testing.assert_array_equal(got, want)

    from zmq_clients import Dealer
    with Dealer(all_transports.transport_ports["zmq"]) as dealer:
        raw = {cam: {"data": img.tobytes(), "shape": list(img.shape)} for cam, img in frames().items()}
        dealer.send({"instruction": TASK, "state": STATE["arm"] + STATE["gripper"] + STATE["base"], "images": raw,
                     "seed": 5})
        reply = dealer.recv()
    assert reply["status"] == 200, reply
    np.testing.assert_array_equal(np.asarray(reply["actions"], np.float32), want)

    tritonclient_http = pytest.importorskip("tritonclient.http")
    client = tritonclient_http.InferenceServerClient(f"127.0.0.1:{all_transports.port}", network_timeout=120.0)
    meta = client.get_model_metadata("gr00t")
    assert {t["name"] for t in meta["inputs"]} >= {"image.front", "image.wrist", "state", "instruction"}
    tensors = [("instruction", np.array([TASK.encode()], dtype=np.object_), "BYTES"),
               ("state", np.asarray([STATE["arm"] + STATE["gripper"] + STATE["base"]], np.float32), "FP32"),
               ("image.front", frames()["front"][None], "UINT8"), ("image.wrist", frames()["wrist"][None], "UINT8"),
               ("seed", np.asarray([5], np.int64), "INT64")]
    inputs = []
    for name, array, datatype in tensors:
        t = tritonclient_http.InferInput(name, list(array.shape), datatype)
        t.set_data_from_numpy(array, binary_data=True)
        inputs.append(t)
    result = client.infer("gr00t", inputs)
    np.testing.assert_array_equal(result.as_numpy("actions")[0], want)


def test_a_missing_camera_is_refused_on_every_transport(all_transports):
    from zmq_clients import Dealer
    with Dealer(all_transports.transport_ports["zmq"]) as dealer:
        img = frames()["front"]
        dealer.send({"instruction": TASK, "state": STATE["arm"] + STATE["gripper"] + STATE["base"],
                     "images": {"front": {"data": img.tobytes(), "shape": list(img.shape)}}})
        reply = dealer.recv()
    assert reply["status"] == 400 and reply["error"]["code"] == "missing_field", reply
    assert "wrist" in reply["error"]["message"]
    # The server goes on serving.
    assert http_act(all_transports.port, 6).shape == (CHUNK, 7)


# -- tether go --model gr00t-n1.7 from a hub ------------------------------------------------------------------------

def test_go_pulls_exports_and_serves_one_embodiment(tmp_path):
    """The registry's gr00t-n1.7 served by a local hub: the fixture checkpoint as nvidia/GR00T-N1.7-3B (its config
    naming the real backbone id) and the stand-in backbone files as nvidia/Cosmos-Reason2-2B."""

    ckpt = tmp_path / "repo"
    shutil.copytree(CASE / "checkpoint", ckpt)
    config = json.loads((ckpt / "config.json").read_text())
    backbone = next((HUB / "models--tether-fixtures--cosmos-reason2-tiny" / "snapshots").iterdir())
    config["model_name"] = "nvidia/Cosmos-Reason2-2B"
    (ckpt / "config.json").write_text(json.dumps(config, indent=2))
    hub = subprocess.Popen([sys.executable, str(REPO / "tests" / "hub" / "fake_hub.py"),
                            "--repo", f"nvidia/GR00T-N1.7-3B={ckpt}",
                            "--repo", f"nvidia/Cosmos-Reason2-2B={backbone.resolve()}"],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        url = json.loads(hub.stdout.readline())["hub"]
        env = {"HF_ENDPOINT": url, "HF_HUB_CACHE": str(tmp_path / "hf"), "HF_HOME": str(tmp_path / "hf_home"),
               "HF_HUB_OFFLINE": "", "TETHER_CACHE": str(tmp_path / "tether")}
        proc = ServeProcess(["--embodiment-tag", "new_embodiment", "--precision", "fp32"], env=env,
                            command=["go", "--model", "gr00t-n1.7"], start_timeout=120.0)
        try:
            cfg = json.loads(request(proc.port, "GET", "/config")[2])
            assert cfg["family"] == "gr00t_n17"
            assert http_act(proc.port, 3).shape == (CHUNK, 7)
        finally:
            assert proc.stop() == 0, proc.stderr_tail()
        err = proc.stderr_tail(20000)
        assert "is not on disk: pulling it" in err and "export verified" in err, err
        exports = list((tmp_path / "tether" / "exports").glob("*/gr00t-n1.7-fp32-new_embodiment"))
        assert len(exports) == 1, err
        assert json.loads((exports[0] / "embodiment_id.json").read_text()) == {"new_embodiment": 1}
        # Without a tag the checkpoint's embodiments are listed.
        out = subprocess.run([str(binary_path()), "go", "--model", "gr00t-n1.7", "--port", "0", "--precision", "fp32"],
                             env={**os.environ, **env}, capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and "--embodiment-tag (libero_sim, new_embodiment)" in out.stderr, out.stderr
    finally:
        hub.stdin.close()
        hub.wait(timeout=10)


def test_rtc_keeps_the_delayed_actions_on_the_leftover(all_transports):
    """GR00T's own RTC: the first inference_delay actions of the new chunk are the leftover's (they stay fixed in
    the sampler), the rest moves on."""
    prev = http_act(all_transports.port, 21)
    leftover = prev[2:]  # 2 actions executed
    images = {cam: {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}
              for cam, img in frames().items()}
    body = json.dumps({"instruction": TASK, "state": STATE["arm"] + STATE["gripper"] + STATE["base"],
                       "images": images, "seed": 22,
                       "rtc": {"prev_actions": leftover.tolist(), "inference_delay": 2}}).encode()
    status, _, raw = request(all_transports.port, "POST", "/act", body, {"Content-Type": "application/json"})
    assert status == 200, raw[:300]
    new = np.asarray(json.loads(raw)["actions"], np.float32)
    np.testing.assert_allclose(new[:2], leftover[:2], atol=1e-5 * max(1.0, float(np.abs(leftover).max())))
    plain = http_act(all_transports.port, 22)
    assert np.abs(new[:2] - leftover[:2]).max() < np.abs(plain[:2] - leftover[:2]).max()


# -- the safety wedges and traces on a GR00T checkpoint -------------------------------------------------------------

def act_body(seed: int, task: str = TASK) -> bytes:
    images = {cam: {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}
              for cam, img in frames().items()}
    return json.dumps({"instruction": task, "state": STATE["arm"] + STATE["gripper"] + STATE["base"],
                       "images": images, "seed": seed}).encode()


def post(port: int, body: bytes):
    status, _, raw = request(port, "POST", "/act", body, {"Content-Type": "application/json"})
    return status, json.loads(raw)


def test_guard_adaptive_steps_and_traces(tmp_path):
    # A 7-joint arm (6 + gripper) allowing |x| <= 0.05 and 0.2 units/s: the model's chunk goes past both.
    joints = [{"name": f"j{i}", "min": -0.05, "max": 0.05, "min_position": -0.05, "max_position": 0.05,
               "max_velocity": 0.2} for i in range(7)]
    arm = tmp_path / "arm.json"
    arm.write_text(json.dumps({"name": "test-arm", "description": "7 values", "units": "rad",
                               "control_rate_hz": 10, "source": "test", "joints": joints}))
    audit, traces = tmp_path / "audit.jsonl", tmp_path / "traces"
    proc = ServeProcess(["--embodiment-tag", "new_embodiment", "--custom-embodiment-config", str(arm),
                         "--audit-log", str(audit), "--adaptive-threshold", "0.5", "--record", str(traces),
                         "--record-fsync", "every_line"], env={"HF_HUB_CACHE": str(HUB)}, checkpoint=CASE / "checkpoint")
    try:
        status, a = post(proc.port, act_body(1))
        assert status == 200, a
        assert a["guard_clamped"] is True and a["guard_violations"], a
        actions = np.asarray(a["actions"])
        assert np.abs(actions).max() <= 0.05 + 1e-5
        assert np.abs(np.diff(actions, axis=0)).max() <= 0.02 + 1e-5
        assert 1 <= a["denoise_steps_used"] <= 4
        bad = json.loads(act_body(2))
        bad["state"] = [1.0, 2.0]
        status, err = post(proc.port, json.dumps(bad).encode())
        assert status == 400 and err["error"]["code"] == "invalid_state", err
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
    assert a["request_id"] in audit.read_text()
    out = subprocess.run([str(binary_path()), "traces", "query", "--dir", str(traces), "--output",
                          str(tmp_path / "records.json")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    records = json.loads((tmp_path / "records.json").read_text())
    assert len(records) == 2, records
    assert records[0]["task"] == TASK and records[0]["status"] == "success"
    assert records[1]["http_status"] == 400


def test_deadline_answers_with_the_last_good_chunk():
    proc = ServeProcess(["--embodiment-tag", "new_embodiment", "--deadline-ms", "150", "--inject-latency-ms", "700"],
                        env={"HF_HUB_CACHE": str(HUB)}, checkpoint=CASE / "checkpoint")
    try:
        status, first = post(proc.port, act_body(3))
        assert status == 504 and first["error"]["code"] == "deadline_exceeded", first
        time.sleep(1.2)  # the late pass finishes and becomes the last good chunk
        status, second = post(proc.port, act_body(3))
        assert status == 200, second
        assert second["action_source"] == "last_good" and second["deadline_exceeded"] is True
        assert second["advanced_steps"] >= 1 and len(second["actions"]) == CHUNK
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
