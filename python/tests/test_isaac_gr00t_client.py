"""Isaac-GR00T's own client (`gr00t.policy.server_client.PolicyClient`) against `tether serve --gr00t-port`.

Isaac-GR00T is not on PyPI, so this runs only from a checkout of it: `scripts/check_isaac_gr00t.sh <checkout>` sets
TETHER_ISAAC_GR00T and runs this file; elsewhere it is skipped. The client needs only numpy, msgpack and pyzmq, which
the test virtualenv has; its modules are imported from the checkout as they are.

The server serves the two embodiments of the N1.6 decode fixture (`relative_arm`: RELATIVE EEF XYZ_ROT6D and NON_EEF
action groups; `mean_std_arm`: mean/std action groups) with an API key. What is checked, through the real client:
- `get_modality_config` decodes into Isaac-GR00T's own ModalityConfig and ActionConfig objects, equal to the
  checkpoint's `processor_config.json` read by Isaac-GR00T's classes;
- an observation laid out as Isaac-GR00T's open-loop evaluation lays it out from that config
  (`parse_observation_gr00t`: video [B, T, H, W, C] uint8, state [B, T, D] float32, language {key: [[text]]})
  gets one action array per action group, [B, horizon, dim], equal to HTTP /act for the same seed and embodiment;
- `reset`, `ping`, a wrong API token and a bad observation come back as the client expects (the last two raise its
  `RuntimeError("Server error: ...")`), and the server keeps serving.
"""

from __future__ import annotations

import base64
import json
import os
import sys

import numpy as np
import pytest

from pngutil import decode_png_rgb8
from serve_process import REPO, ServeProcess, binary_path, hub_cache_holding, request

ISAAC = os.environ.get("TETHER_ISAAC_GR00T", "")
pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not ISAAC, reason="set TETHER_ISAAC_GR00T to an Isaac-GR00T checkout "
                                         "(scripts/check_isaac_gr00t.sh does)"),
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

ROOT = REPO / "tests" / "fixtures" / "gr00t_n16_decode"
EAGLE = REPO / "tests" / "fixtures" / "gr00t_n16" / "eagle"
KEY = "sesame"
TASK = "stack the blocks"
FRAMES = {"relative_arm": {"front": "front.png", "wrist": "wrist.png"}, "mean_std_arm": {"image": "image.png"}}


@pytest.fixture(scope="module")
def isaac():
    if ISAAC not in sys.path:
        sys.path.insert(0, ISAAC)
    from gr00t.data.types import ActionConfig, ModalityConfig
    from gr00t.policy.server_client import PolicyClient
    return {"PolicyClient": PolicyClient, "ModalityConfig": ModalityConfig, "ActionConfig": ActionConfig}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    # The checkpoint names Isaac-GR00T's Eagle directory; a hub cache holds the fixture's stand-in under that id.
    hub = hub_cache_holding(tmp_path_factory.mktemp("eagle_hub"), "nvidia/Eagle-Block2A-2B-v2", EAGLE)
    proc = ServeProcess(["--gr00t-port", "0", "--embodiment-tag", "relative_arm,mean_std_arm"],
                        env={"HF_HUB_CACHE": str(hub), "TETHER_API_KEY": KEY}, checkpoint=ROOT / "checkpoint")
    try:
        yield proc
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


@pytest.fixture
def client(isaac, server):
    c = isaac["PolicyClient"](host="127.0.0.1", port=server.transport_ports["gr00t"], timeout_ms=60000,
                              api_token=KEY)
    yield c
    del c


def own_modality_config(tag):
    processor = json.loads((ROOT / "checkpoint" / "processor_config.json").read_text())
    return processor["processor_kwargs"]["modality_configs"][tag]


def group_dims(tag, modality):
    stats = json.loads((ROOT / "checkpoint" / "statistics.json").read_text())[tag][modality]
    return {key: len(value["min"]) for key, value in stats.items()}


def observation(cfg, tag):
    """What Isaac-GR00T's open-loop evaluation sends (parse_observation_gr00t over the modality config)."""
    frames = {cam: decode_png_rgb8((ROOT / "cases" / tag / "inputs" / name).read_bytes())
              for cam, name in FRAMES[tag].items()}
    dims = group_dims(tag, "state")
    rng = np.random.default_rng(7)
    state = {key: rng.uniform(-0.5, 0.5, (1, 1, dims[key])).astype(np.float32) for key in cfg["state"].modality_keys}
    return {"video": {key: frames[key][None, None] for key in cfg["video"].modality_keys},
            "state": state,
            "language": {key: [[TASK]] for key in cfg["language"].modality_keys}}


def http_act(port, tag, obs, seed):
    images = {cam: {"data": base64.b64encode(img[0, 0].tobytes()).decode(), "shape": list(img[0, 0].shape)}
              for cam, img in obs["video"].items()}
    state = np.concatenate([v[0, 0] for v in obs["state"].values()]).tolist()
    body = json.dumps({"instruction": TASK, "state": state, "images": images, "seed": seed,
                       "embodiment_tag": tag}).encode()
    status, _, raw = request(port, "POST", "/act", body,
                             {"Content-Type": "application/json", "Authorization": f"Bearer {KEY}"})
    assert status == 200, raw[:300]
    return np.asarray(json.loads(raw)["actions"], np.float32)


@pytest.mark.parametrize("tag", ["relative_arm", "mean_std_arm"])
def test_modality_config_decodes_into_isaac_gr00t_classes(isaac, client, tag):
    cfg = client.call_endpoint("get_modality_config", {"options": {"embodiment_tag": tag}})
    own = own_modality_config(tag)
    for modality in ("video", "state", "action", "language"):
        assert isinstance(cfg[modality], isaac["ModalityConfig"]), modality
        assert cfg[modality] == isaac["ModalityConfig"](**own[modality]), modality
    assert all(isinstance(a, isaac["ActionConfig"]) for a in cfg["action"].action_configs)
    reps = [a.rep.name for a in cfg["action"].action_configs]
    assert reps == (["RELATIVE", "RELATIVE", "ABSOLUTE"] if tag == "relative_arm" else ["ABSOLUTE"] * 3)
    if tag == "relative_arm":
        assert cfg["action"].action_configs[0].format.name == "XYZ_ROT6D"
        assert cfg["action"].action_configs[0].state_key == "eef"
    else:
        assert cfg["action"].mean_std_embedding_keys == ["xyz", "rpy"]


@pytest.mark.parametrize("tag", ["relative_arm", "mean_std_arm"])
def test_get_action_from_the_open_loop_layout_matches_http(client, server, tag):
    cfg = client.call_endpoint("get_modality_config", {"options": {"embodiment_tag": tag}})
    obs = observation(cfg, tag)
    action, info = client.get_action(obs, options={"embodiment_tag": tag, "seed": 11})
    dims = group_dims(tag, "action")
    horizon = len(cfg["action"].delta_indices)
    assert list(action) == cfg["action"].modality_keys
    for key, value in action.items():
        assert isinstance(value, np.ndarray) and value.dtype == np.float32
        assert value.shape == (1, horizon, dims[key]), key
    assert isinstance(info, dict)
    want = http_act(server.port, tag, obs, seed=11)
    np.testing.assert_array_equal(np.concatenate([action[k][0] for k in cfg["action"].modality_keys], axis=1), want)
    # The open-loop evaluation's own unbatching (parse_action_gr00t): one [horizon, dim] array per "action.<group>".
    unbatched = {f"action.{k}": v[0] for k, v in action.items()}
    assert all(unbatched[f"action.{k}"].shape == (horizon, dims[k]) for k in cfg["action"].modality_keys)


def test_reset_ping_and_errors_as_the_client_expects(isaac, client, server):
    assert client.ping() is True
    assert client.reset() == {}
    assert client.reset(options={"episode_id": "e1", "embodiment_tag": "relative_arm"}) == {}
    wrong = isaac["PolicyClient"](host="127.0.0.1", port=server.transport_ports["gr00t"], api_token="wrong")
    with pytest.raises(RuntimeError, match="Server error: Unauthorized"):
        wrong.get_modality_config()
    del wrong
    cfg = client.call_endpoint("get_modality_config", {"options": {"embodiment_tag": "relative_arm"}})
    obs = observation(cfg, "relative_arm")
    del obs["state"]["joints"]
    with pytest.raises(RuntimeError, match="Server error: .*joints"):
        client.get_action(obs, options={"embodiment_tag": "relative_arm"})
    obs = observation(cfg, "relative_arm")
    obs["state"]["eef"] = np.full_like(obs["state"]["eef"], np.nan)
    with pytest.raises(RuntimeError, match="Server error: "):
        client.get_action(obs, options={"embodiment_tag": "relative_arm"})
    # Still serving, on the same client.
    assert client.ping() is True
    action, _ = client.get_action(observation(cfg, "relative_arm"), options={"embodiment_tag": "relative_arm"})
    assert set(action) == {"eef", "joints", "gripper"}
