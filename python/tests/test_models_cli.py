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
FIGURE = {"benchmark": "LIBERO-10 / LIBERO-Long", "metric": "success rate (%)", "value": 71, "setting": "fine-tuned on LIBERO-10",
          "source": {"title": "Tiny's paper", "url": "https://example.org/tiny"}}


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
                 "files": ["config.json", "model.safetensors"], "figures": [FIGURE]},
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


def test_figures_in_list_and_info(env):
    listed = {m["id"]: m for m in json.loads(tether(["models", "list", "--json"], env).stdout)}
    assert listed["tiny"]["published"] == "LIBERO-10 71%" and listed["tiny"]["figures"] == [FIGURE]
    assert listed["gated"]["published"] is None and listed["gated"]["figures"] == []
    table = tether(["models", "list"], env).stdout.splitlines()
    assert "published" in table[0]
    assert "LIBERO-10 71%" in next(line for line in table if line.startswith("tiny "))
    info = tether(["models", "info", "tiny"], env).stdout
    assert "published    LIBERO-10 / LIBERO-Long: 71% success rate \u2014 fine-tuned on LIBERO-10" in info
    assert "source: Tiny's paper, https://example.org/tiny" in info


def test_shipped_registry_has_the_fluxvla_finetune():
    shipped = {k: v for k, v in os.environ.items() if k != "TETHER_REGISTRY"}
    info = json.loads(tether(["models", "info", "pi05-libero10-fluxvla", "--json"], shipped).stdout)
    assert (info["hf_repo"], info["subfolder"]) == ("limxdynamics/FluxVLAEngine", "pi05_paligemma_libero_10_full_finetune_bs64")
    assert info["family"] == "pi05_fluxvla" and info["supported"] is True
    assert info["figures"][0]["benchmark"] == "LIBERO-10 / LIBERO-Long" and info["figures"][0]["value"] == 95.6


def test_malformed_figure_names_entry_and_field(env, tmp_path):
    bad = dict(FIGURE, source={"title": "no address"})
    registry = tmp_path / "bad.json"
    registry.write_text(json.dumps({"models": {"tiny": {"family": "smolvla", "hf_repo": "a/b", "figures": [FIGURE, bad]}}}))
    r = tether(["models", "list"], dict(env, TETHER_REGISTRY=str(registry)))
    assert r.returncode == 2
    assert f"{registry}: models.tiny.figures[1].source: missing field 'url'" in r.stderr, r.stderr


def test_pull_of_a_subfolder_entry_fetches_only_that_folder(env, tmp_path):
    registry = tmp_path / "nested.json"
    registry.write_text(json.dumps({"models": {
        "nested": {"family": "smolvla", "hf_repo": "tether-test/tiny", "subfolder": "sub/dir"}}}))
    e = dict(env, TETHER_REGISTRY=str(registry))
    assert json.loads(tether(["models", "list", "--json"], e).stdout)[0]["local_path"] is None
    r = tether(["models", "pull", "nested"], e)
    assert r.returncode == 0, r.stderr
    folder = Path(r.stdout.strip())
    assert folder.parts[-2:] == ("sub", "dir") and folder.parents[2].name == "snapshots"
    assert [p.name for p in folder.iterdir()] == ["notes.txt"]
    assert not (folder.parents[1] / "model.safetensors").exists()  # the rest of the repo stays on the hub
    assert json.loads(tether(["models", "list", "--json"], e).stdout)[0]["local_path"] == str(folder)
