"""A GR00T N1.7 checkpoint (the oracle fixture `tests/fixtures/gr00t_n17/cam2_new`) served by the real binary with
`--embodiment-tag`: the GR00T ZMQ transport reports the embodiment's modality config (its cameras and its state and
action groups, as the checkpoint's processor_config.json names them), answers get_action per action group, and agrees
with HTTP /act on the same seed; an observation missing a group or a camera is a clear error."""

from __future__ import annotations

import base64
import json

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
