"""Several embodiments of one GR00T N1.7 checkpoint served by one process (`--embodiment-tag libero_sim,new_embodiment`):
each request names its embodiment (HTTP and Tether ZMQ `embodiment_tag`, GR00T ZMQ `options.embodiment_tag`, openpi's
`?embodiment_tag=` on the connection, KServe `parameters.embodiment_tag`) and gets, bit for bit, what a server of that
embodiment alone answers; the first tag is the default; an unknown tag is a 400 listing the served ones on every
transport, and the server goes on serving; /config, /health and get_modality_config describe each embodiment; traces
go to one directory (one hash chain) per embodiment and name it."""

from __future__ import annotations

import base64
import json
import subprocess

import numpy as np
import pytest

msgpack = pytest.importorskip("msgpack")
zmq = pytest.importorskip("zmq")

from pngutil import decode_png_rgb8  # noqa: E402
from serve_process import REPO, ServeProcess, binary_path, request  # noqa: E402
from zmq_clients import Dealer, Gr00tClient, trace_lines  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

FIXTURES = REPO / "tests" / "fixtures" / "gr00t_n17"
CHECKPOINT = FIXTURES / "cam1_libero" / "checkpoint"  # two embodiments: libero_sim and new_embodiment
HUB = REPO / "tests" / "fixtures" / "gr00t_hub"
TASK = "put the bowl on the plate"

# Each embodiment's cameras (frames from the oracle cases) and state, in its modality order.
EMBODIMENTS = {
    "libero_sim": {"frames": {"image": FIXTURES / "cam1_libero" / "inputs" / "image.png"},
                   "state": [0.1, -0.2, 0.3, 0.0, 0.1, -0.1, 0.5], "groups": ["x", "y", "z", "roll", "pitch", "yaw",
                                                                            "gripper"]},
    "new_embodiment": {"frames": {"front": FIXTURES / "cam2_new" / "inputs" / "front.png",
                                  "wrist": FIXTURES / "cam2_new" / "inputs" / "wrist.png"},
                       "state": [0.1, 0.2, 0.3, 0.1, 0.2, 0.3, 0.5, 0.1, 0.2], "groups": ["arm", "gripper"]},
}


def frames(tag):
    return {cam: decode_png_rgb8(path.read_bytes()) for cam, path in EMBODIMENTS[tag]["frames"].items()}


def act_body(tag, seed, name_it=True):
    images = {cam: {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}
              for cam, img in frames(tag).items()}
    body = {"instruction": TASK, "state": EMBODIMENTS[tag]["state"], "images": images, "seed": seed}
    if name_it:
        body["embodiment_tag"] = tag
    return json.dumps(body).encode()


def post(port, body):
    status, _, raw = request(port, "POST", "/act", body, {"Content-Type": "application/json"})
    return status, json.loads(raw)


def http_act(port, tag, seed, name_it=True):
    status, answer = post(port, act_body(tag, seed, name_it))
    assert status == 200, answer
    return np.asarray(answer["actions"], np.float32)


@pytest.fixture(scope="module")
def record_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("record")


@pytest.fixture(scope="module")
def multi(tmp_path_factory, record_dir):
    layouts = tmp_path_factory.mktemp("openpi")
    # openpi's key layout is the robot's client's: each embodiment gets its own (--openpi-layout TAG=FILE).
    (layouts / "new.json").write_text(json.dumps({"images": {"cams/front": "front", "cams/wrist": "wrist"},
                                                  "state": ["state"], "prompt": "task"}))
    (layouts / "libero.json").write_text(json.dumps({"images": {"agentview": "image"}, "state": ["robot_state"],
                                                     "prompt": "instruction"}))
    proc = ServeProcess(["--embodiment-tag", "libero_sim,new_embodiment", "--gr00t-port", "0", "--zmq-port", "0",
                         "--openpi-port", "0", "--openpi-layout", f"new_embodiment={layouts / 'new.json'}",
                         "--openpi-layout", f"libero_sim={layouts / 'libero.json'}", "--model-name", "gr00t",
                         "--record", str(record_dir)],
                        env={"HF_HUB_CACHE": str(HUB)}, checkpoint=CHECKPOINT)
    try:
        yield proc
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


@pytest.fixture(scope="module")
def alone():
    """What a server of each embodiment alone answers, per seed."""
    answers = {}
    for tag in EMBODIMENTS:
        proc = ServeProcess(["--embodiment-tag", tag], env={"HF_HUB_CACHE": str(HUB)}, checkpoint=CHECKPOINT)
        try:
            answers[tag] = {seed: http_act(proc.port, tag, seed, name_it=False) for seed in (3, 4)}
        finally:
            assert proc.stop() == 0, proc.stderr_tail()
    return answers


def test_config_and_health_describe_each_embodiment(multi):
    cfg = json.loads(request(multi.port, "GET", "/config")[2])
    assert cfg["embodiment"] == "libero_sim" and cfg["embodiments"] == ["libero_sim", "new_embodiment"]
    assert cfg["cameras"] == ["image"] and cfg["state_dim"] == 7
    other = json.loads(request(multi.port, "GET", "/config?embodiment_tag=new_embodiment")[2])
    assert other["embodiment"] == "new_embodiment"
    assert other["cameras"] == ["front", "wrist"] and other["state_dim"] == 9 and other["action_dim"] == 7
    assert [g["name"] for g in other["state_groups"]] == ["arm", "gripper", "base"]
    assert other["action_groups"] == [{"name": "arm", "dim": 6}, {"name": "gripper", "dim": 1}]
    assert other["modality_config"]["action"]["modality_keys"] == ["arm", "gripper"]
    assert cfg["modality_config"]["video"]["modality_keys"] == ["image"]
    status, _, raw = request(multi.port, "GET", "/config?embodiment_tag=nope")
    assert status == 400 and json.loads(raw)["error"]["code"] == "unknown_embodiment"
    health = json.loads(request(multi.port, "GET", "/health")[2])
    assert health["state"] == "ready"
    assert {tag: e["state"] for tag, e in health["embodiments"].items()} == {"libero_sim": "ready",
                                                                          "new_embodiment": "ready"}


def test_http_routes_by_tag_and_matches_each_embodiment_alone(multi, alone):
    for tag in EMBODIMENTS:
        for seed in (3, 4):
            np.testing.assert_array_equal(http_act(multi.port, tag, seed), alone[tag][seed])
    # No tag: the first one.
    np.testing.assert_array_equal(http_act(multi.port, "libero_sim", 3, name_it=False), alone["libero_sim"][3])
    # An observation of one embodiment sent to the other: that embodiment's own error.
    body = json.loads(act_body("libero_sim", 3))
    body["embodiment_tag"] = "new_embodiment"
    status, answer = post(multi.port, json.dumps(body).encode())
    assert status == 400 and answer["error"]["code"] in ("invalid_state", "unknown_camera"), answer


def test_an_unknown_tag_is_refused_on_every_transport_and_lists_the_served_ones(multi, alone):
    body = json.loads(act_body("libero_sim", 3))
    body["embodiment_tag"] = "unitree_g1"
    status, answer = post(multi.port, json.dumps(body).encode())
    assert status == 400 and answer["error"]["code"] == "unknown_embodiment", answer
    assert "libero_sim, new_embodiment" in answer["error"]["message"]
    body["embodiment_tag"] = 7
    status, answer = post(multi.port, json.dumps(body).encode())
    assert status == 400 and answer["error"]["code"] == "invalid_field" and "embodiment_tag" in answer["error"]["message"]

    with Dealer(multi.transport_ports["zmq"]) as dealer:
        raw = {cam: {"data": img.tobytes(), "shape": list(img.shape)} for cam, img in frames("libero_sim").items()}
        dealer.send({"instruction": TASK, "state": EMBODIMENTS["libero_sim"]["state"], "images": raw,
                     "embodiment_tag": "unitree_g1"})
        reply = dealer.recv()
    assert reply["status"] == 400 and reply["error"]["code"] == "unknown_embodiment", reply

    with Gr00tClient(multi.transport_ports["gr00t"]) as client:
        err = client.call("get_modality_config", {"options": {"embodiment_tag": "unitree_g1"}})
        assert err["status"] == 400 and "libero_sim, new_embodiment" in err["error"], err
        obs = {"video": {cam: img[None, None] for cam, img in frames("libero_sim").items()},
               "state": {g: np.asarray([v], np.float32)[None, None]
                         for g, v in zip(EMBODIMENTS["libero_sim"]["groups"], EMBODIMENTS["libero_sim"]["state"])},
               "language": {"task": [[TASK]]}}
        err = client.get_action(obs, {"embodiment_tag": "unitree_g1"})
        assert err["status"] == 400 and "unknown embodiment tag" in err["error"], err

    websockets_client = pytest.importorskip("websockets.sync.client")
    with pytest.raises(Exception) as refused:
        websockets_client.connect(f"ws://127.0.0.1:{multi.transport_ports['openpi']}/?embodiment_tag=unitree_g1")
    assert "400" in str(refused.value)

    tritonclient_http = pytest.importorskip("tritonclient.http")
    client = tritonclient_http.InferenceServerClient(f"127.0.0.1:{multi.port}", network_timeout=120.0)
    with pytest.raises(Exception) as failed:
        client.infer("gr00t", kserve_inputs(tritonclient_http, "libero_sim", 3),
                     parameters={"embodiment_tag": "unitree_g1"})
    assert "unknown embodiment tag" in str(failed.value)
    # Still serving.
    np.testing.assert_array_equal(http_act(multi.port, "libero_sim", 3), alone["libero_sim"][3])


def kserve_inputs(tritonclient_http, tag, seed):
    tensors = [("instruction", np.array([TASK.encode()], dtype=np.object_), "BYTES"),
               ("state", np.asarray([EMBODIMENTS[tag]["state"]], np.float32), "FP32"),
               ("seed", np.asarray([seed], np.int64), "INT64")]
    tensors += [(f"image.{cam}", img[None], "UINT8") for cam, img in frames(tag).items()]
    inputs = []
    for name, array, datatype in tensors:
        t = tritonclient_http.InferInput(name, list(array.shape), datatype)
        t.set_data_from_numpy(array, binary_data=True)
        inputs.append(t)
    return inputs


# openpi_client 0.1.2 keeps the connection outside a `with` block, which websockets 14+ warns about.
@pytest.mark.filterwarnings("ignore:connect\\(\\) must be used as a context manager:DeprecationWarning")
def test_every_transport_routes_by_tag(multi, alone):
    tag, seed = "new_embodiment", 4
    want = alone[tag][seed]

    with Dealer(multi.transport_ports["zmq"]) as dealer:
        raw = {cam: {"data": img.tobytes(), "shape": list(img.shape)} for cam, img in frames(tag).items()}
        dealer.send({"instruction": TASK, "state": EMBODIMENTS[tag]["state"], "images": raw, "seed": seed,
                     "embodiment_tag": tag})
        reply = dealer.recv()
    assert reply["status"] == 200, reply
    np.testing.assert_array_equal(np.asarray(reply["actions"], np.float32), want)

    with Gr00tClient(multi.transport_ports["gr00t"]) as client:
        cfg = client.call("get_modality_config", {"options": {"embodiment_tag": tag}})
        assert cfg["video"]["modality_keys"] == ["front", "wrist"]
        assert cfg["state"]["modality_keys"] == ["arm", "gripper", "base"]
        default = client.call("get_modality_config", requires_input=False)
        assert default["video"]["modality_keys"] == ["image"]
        state = EMBODIMENTS[tag]["state"]
        obs = {"video": {cam: img[None, None] for cam, img in frames(tag).items()},
               "state": {"arm": np.asarray(state[:6], np.float32)[None, None],
                         "gripper": np.asarray(state[6:7], np.float32)[None, None],
                         "base": np.asarray(state[7:], np.float32)[None, None]},
               "language": {"task": [[TASK]]}}
        actions, _ = client.get_action(obs, {"seed": seed, "embodiment_tag": tag})
        np.testing.assert_array_equal(np.concatenate([actions["arm"][0], actions["gripper"][0]], axis=1), want)
        assert client.call("reset", {"options": {"embodiment_tag": tag}}) == {}

    websocket_client_policy = pytest.importorskip("openpi_client.websocket_client_policy")
    policy = websocket_client_policy.WebsocketClientPolicy(
        f"ws://127.0.0.1:{multi.transport_ports['openpi']}/?embodiment_tag={tag}")
    assert policy.get_server_metadata()["embodiment_tag"] == tag
    obs = {f"cams/{cam}": img for cam, img in frames(tag).items()}
    obs.update({"state": np.asarray(EMBODIMENTS[tag]["state"]), "task": TASK, "seed": seed})
    np.testing.assert_array_equal(np.asarray(policy.infer(obs)["actions"], np.float32), want)
    # The default embodiment's connection reads its own robot's keys.
    policy = websocket_client_policy.WebsocketClientPolicy(f"ws://127.0.0.1:{multi.transport_ports['openpi']}")
    assert policy.get_server_metadata()["layout"].endswith("libero.json")
    obs = {"agentview": frames("libero_sim")["image"], "robot_state": np.asarray(EMBODIMENTS["libero_sim"]["state"]),
           "instruction": TASK, "seed": 3}
    np.testing.assert_array_equal(np.asarray(policy.infer(obs)["actions"], np.float32), alone["libero_sim"][3])

    tritonclient_http = pytest.importorskip("tritonclient.http")
    client = tritonclient_http.InferenceServerClient(f"127.0.0.1:{multi.port}", network_timeout=120.0)
    meta = client.get_model_metadata("gr00t")
    assert meta["parameters"]["embodiments"] == ["libero_sim", "new_embodiment"]
    result = client.infer("gr00t", kserve_inputs(tritonclient_http, tag, seed), parameters={"embodiment_tag": tag})
    np.testing.assert_array_equal(result.as_numpy("actions")[0], want)


def test_traces_are_kept_per_embodiment(multi, record_dir):
    http_act(multi.port, "libero_sim", 3)
    http_act(multi.port, "new_embodiment", 3)
    for tag in EMBODIMENTS:
        lines = trace_lines(record_dir / tag)
        assert lines and all(line["embodiment"] == tag for line in lines), lines[-1:]
    out = subprocess.run([str(binary_path()), "traces", "verify", "--dir", str(record_dir / "new_embodiment")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr


def test_a_robot_file_can_be_one_embodiments_own(tmp_path, alone):
    """`--custom-embodiment-config new_embodiment=FILE`: that robot's guard clamps its actions to the file's limits,
    the other embodiment is left as a server of it alone answers, and /metrics counts the clamps by embodiment."""
    limit = 0.05
    robot = tmp_path / "tight_arm.json"
    robot.write_text(json.dumps({"name": "tight_arm", "units": "rad", "control_rate_hz": 10, "joints": [
        {"name": f"j{i}", "min": -limit, "max": limit} for i in range(7)]}))
    proc = ServeProcess(["--embodiment-tag", "libero_sim,new_embodiment",
                         "--custom-embodiment-config", f"new_embodiment={robot}",
                         "--audit-log", str(tmp_path / "audit.jsonl")],
                        env={"HF_HUB_CACHE": str(HUB)}, checkpoint=CHECKPOINT)
    try:
        np.testing.assert_array_equal(http_act(proc.port, "libero_sim", 3), alone["libero_sim"][3])
        clamped = http_act(proc.port, "new_embodiment", 3)
        free = alone["new_embodiment"][3]
        assert np.abs(free).max() > limit, "the limits must bite for this test to mean anything"
        np.testing.assert_array_equal(clamped, np.clip(free, -limit, limit))
        metrics = request(proc.port, "GET", "/metrics")[2].decode()
        assert 'tether_guard_clamped_total{embodiment="new_embodiment"} 1\n' in metrics, metrics
        assert 'tether_guard_clamped_total{embodiment="libero_sim"}' not in metrics, "no guard without a robot file"
        assert 'tether_episodes{embodiment="libero_sim"} 1\n' in metrics, metrics
        audit = [json.loads(line) for line in (tmp_path / "audit.jsonl").read_text().splitlines()]
        assert audit and all(line["embodiment"] == "new_embodiment" for line in audit), audit[:2]
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
