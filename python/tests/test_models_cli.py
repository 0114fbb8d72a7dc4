"""`tether models list|info|pull` against a local stand-in for the Hugging Face hub (tests/hub/fake_hub.py)."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from serve_process import binary_path

ROOT = Path(__file__).resolve().parents[2]
FAKE_HUB = ROOT / "tests" / "hub" / "fake_hub.py"


@pytest.fixture(scope="module")
def fake_hub():
    proc = subprocess.Popen([sys.executable, str(FAKE_HUB)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    urls = json.loads(proc.stdout.readline())
    yield urls
    proc.stdin.close()
    proc.wait(timeout=10)


@pytest.fixture()
def env(tmp_path, fake_hub):
    registry = tmp_path / "registry.json"
    registry.write_text(json.dumps({"models": {
        "tiny": {"family": "smolvla", "hf_repo": "tether-test/tiny", "parameters": 1000000, "supported": True,
                 "files": ["config.json", "model.safetensors"]},
        "gated": {"family": "smolvla", "hf_repo": "tether-test/gated", "supported": True},
    }}))
    e = dict(os.environ)
    for k in ("HF_TOKEN", "HF_HUB_OFFLINE", "HF_HOME"):
        e.pop(k, None)
    e.update(TETHER_REGISTRY=str(registry), HF_ENDPOINT=fake_hub["hub"], HF_HUB_CACHE=str(tmp_path / "cache"))
    return e


def tether(args, env):
    return subprocess.run([str(binary_path())] + args, env=env, capture_output=True, text=True, timeout=60)


def test_pull_lays_out_the_hub_cache_and_list_sees_it(env):
    before = json.loads(tether(["models", "list", "--json"], env).stdout)
    assert [m["local_path"] for m in before if m["id"] == "tiny"] == [None]
    r = tether(["models", "pull", "tiny"], env)
    assert r.returncode == 0, r.stderr
    snap = Path(r.stdout.strip())
    assert snap.parent.name == "snapshots" and snap.parent.parent.name == "models--tether-test--tiny"
    assert sorted(p.name for p in snap.iterdir()) == ["config.json", "model.safetensors"]  # only the listed files
    assert (snap / "model.safetensors").is_symlink()
    after = json.loads(tether(["models", "list", "--json"], env).stdout)
    assert [m["local_path"] for m in after if m["id"] == "tiny"] == [str(snap)]
    # A second pull is served from the cache, offline too.
    offline = dict(env, HF_HUB_OFFLINE="1")
    again = tether(["models", "pull", "tiny"], offline)
    assert again.returncode == 0 and again.stdout.strip() == str(snap), again.stderr


def test_info_reports_sizes_and_targets(env):
    r = tether(["models", "info", "tiny", "--json", "--target", "orin-nano"], env)
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    assert info["disk_size"]["fp32"] == "4 MB" and info["disk_size"]["bf16"] == "2 MB"
    assert info["targets"] == [{"target": "orin-nano", "fits": True, "precision": "fp16", "memory": "2 MB"}]
    assert tether(["models", "info", "tiny", "--target", "mars-rover"], env).returncode == 2


def test_gated_unknown_and_unreachable_fail_with_one_line(env, tmp_path):
    gated = tether(["models", "pull", "gated"], env)
    assert gated.returncode == 2 and "HF_TOKEN" in gated.stderr, gated.stderr
    unknown = tether(["models", "pull", "nope"], env)
    assert unknown.returncode == 2 and "not in the registry" in unknown.stderr
    closed = dict(env, HF_ENDPOINT="http://127.0.0.1:9", HF_HUB_CACHE=str(tmp_path / "empty"))
    down = tether(["models", "pull", "tiny"], closed)
    assert down.returncode == 2 and "HF_HUB_OFFLINE" in down.stderr, down.stderr
    for r in (gated, unknown, down):  # progress lines aside, the failure is one "error:" line
        assert len([line for line in r.stderr.splitlines() if line.startswith("error:")]) == 1, r.stderr
