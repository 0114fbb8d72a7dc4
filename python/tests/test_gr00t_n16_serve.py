"""A GR00T N1.6 checkpoint (the oracle fixture `tests/fixtures/gr00t_n16`) served by the real binary: the GR00T ZMQ
transport's modality config and per-group actions, equal to HTTP /act on the same seed (parity with the oracle is
tests/policy/test_gr00t_n16_parity.cpp)."""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

msgpack = pytest.importorskip("msgpack")
zmq = pytest.importorskip("zmq")

from pngutil import decode_png_rgb8  # noqa: E402
from serve_process import REPO, ServeProcess, binary_path, hub_cache_holding, request  # noqa: E402
from zmq_clients import Gr00tClient  # noqa: E402

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

ROOT = REPO / "tests" / "fixtures" / "gr00t_n16"
CASE = ROOT / "cases" / "cam2_new_embodiment"
STATE = {"arm": [0.1, -0.2, 0.3, 0.0, 0.5, -0.6], "gripper": [0.4], "base_yaw": [1.2]}
TASK = "pick up the red cube"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    # The checkpoint names Isaac-GR00T's Eagle directory; a hub cache holds the fixture's stand-in under that id.
    hub = hub_cache_holding(tmp_path_factory.mktemp("eagle_hub"), "nvidia/Eagle-Block2A-2B-v2", ROOT / "eagle")
    proc = ServeProcess(["--gr00t-port", "0", "--embodiment-tag", "new_embodiment"], env={"HF_HUB_CACHE": str(hub)},
                        checkpoint=ROOT / "checkpoint")
    try:
        yield proc
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def frames():
    return {cam: decode_png_rgb8((CASE / "inputs" / f"{cam}.png").read_bytes()) for cam in ("front", "wrist")}


def test_modality_config_and_actions_match_http(server):
    with Gr00tClient(server.transport_ports["gr00t"]) as client:
        cfg = client.call("get_modality_config", requires_input=False)
        assert cfg["video"]["modality_keys"] == ["front", "wrist"]
        assert cfg["state"]["modality_keys"] == ["arm", "gripper", "base_yaw"]
        assert cfg["action"]["modality_keys"] == ["arm", "gripper"]
        # As Isaac-GR00T's server answers: the checkpoint's own modality config, action_configs and encodings included.
        own = json.loads((ROOT / "checkpoint" / "processor_config.json").read_text())
        for modality, want in own["processor_kwargs"]["modality_configs"]["new_embodiment"].items():
            assert cfg[modality] == want, modality
        assert cfg["state"]["sin_cos_embedding_keys"] == ["base_yaw"]
        assert cfg["action"]["action_configs"][0]["rep"] == "ABSOLUTE"
        # The observation a client builds from it, the instruction under the checkpoint's language key.
        obs = {"video": {cam: img[None, None] for cam, img in frames().items()},
               "state": {k: np.asarray(v, np.float32)[None, None] for k, v in STATE.items()},
               "language": {cfg["language"]["modality_keys"][0]: [[TASK]]}}
        actions, _ = client.get_action(obs, {"seed": 4})
    assert actions["arm"].shape == (1, 8, 6) and actions["gripper"].shape == (1, 8, 1)
    images = {cam: {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}
              for cam, img in frames().items()}
    body = json.dumps({"instruction": TASK, "state": STATE["arm"] + STATE["gripper"] + STATE["base_yaw"],
                       "images": images, "seed": 4}).encode()
    status, _, raw = request(server.port, "POST", "/act", body, {"Content-Type": "application/json"})
    assert status == 200, raw[:300]
    http = np.asarray(json.loads(raw)["actions"], np.float32)
    np.testing.assert_array_equal(np.concatenate([actions["arm"][0], actions["gripper"][0]], axis=1), http)
    cfg = json.loads(request(server.port, "GET", "/config")[2])
    assert cfg["family"] == "gr00t_n16"
    assert cfg["state_groups"] == [{"name": "arm", "dim": 6}, {"name": "gripper", "dim": 1},
                                   {"name": "base_yaw", "dim": 1}]
    assert cfg["action_groups"] == [{"name": "arm", "dim": 6}, {"name": "gripper", "dim": 1}]
    assert cfg["modality_config"] == own["processor_kwargs"]["modality_configs"]["new_embodiment"]
