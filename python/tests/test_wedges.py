"""Safety wedges through the real `tether serve` binary: embodiments and the action guard with its audit log,
deadlines (a slow model made with --inject-latency-ms), adaptive steps, similarity skips, the circuit breaker (a
model file made to produce NaN, and --inject-failure-file), a second local server as the cloud fallback, episodes,
real-time chunking and trace recording with `tether traces verify`."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import time
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import pytest

from serve_process import DEMO, REPO, ServeProcess, binary_path, metric, parse_metrics, request
from test_serve_integration import STATE, act_body, check_actions, expect_error, ok_json, post_act

pytestmark = [
    pytest.mark.integration,
    pytest.mark.skipif(not binary_path().is_file(), reason=f"tether binary not found at {binary_path()}"),
]

CHUNK, DIM = 50, 6
SO100_JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]


def act(server: ServeProcess, **fields: Any) -> Dict[str, Any]:
    return ok_json(post_act(server, act_body(**fields)))


def metrics_of(server: ServeProcess) -> Dict:
    status, _, body = request(server.port, "GET", "/metrics")
    assert status == 200
    return parse_metrics(body.decode())


def start_fails(args: List[str], checkpoint: Path = DEMO) -> str:
    """Runs `tether serve` expecting it to refuse to start; returns its stderr."""
    proc = subprocess.run([str(binary_path()), "serve", str(checkpoint), "--port", "0", *args],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0, proc.stdout
    return proc.stderr


@pytest.fixture(scope="module")
def plain():
    proc = ServeProcess()
    yield proc
    assert proc.stop() == 0, proc.stderr_tail()


# -- embodiments and the guard --------------------------------------------------------------------------------


def test_embodiment_preset_reports_joints_and_keeps_limits(tmp_path):
    audit = tmp_path / "audit.jsonl"
    proc = ServeProcess(["--embodiment", "so100", "--audit-log", str(audit)])
    try:
        data = act(proc)
        assert data["joint_names"] == SO100_JOINTS
        actions = check_actions(data)
        assert np.all(actions[:, :5] >= -100) and np.all(actions[:, :5] <= 100)
        assert np.all(actions[:, 5] >= 0) and np.all(actions[:, 5] <= 100)
        assert isinstance(data["guard_clamped"], bool) and isinstance(data["guard_violations"], list)
        # Velocity: consecutive rows move at most max_velocity / control rate.
        steps = np.abs(np.diff(actions, axis=0))
        assert np.all(steps[:, :5] <= 150 / 30 + 1e-3) and np.all(steps[:, 5] <= 75 / 30 + 1e-3)
        config = json.loads(request(proc.port, "GET", "/config")[2])
        assert config["wedges"]["embodiment"]["name"] == "so100"
        assert config["wedges"]["control_rate_hz"] == 30
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_safety_config_clamps_and_audits(tmp_path, plain):
    raw = check_actions(act(plain))
    safety = tmp_path / "limits.json"
    safety.write_text(json.dumps({
        "joint_limits": {
            "shoulder_pan": {"has_position_limits": True, "min_position": -5.0, "max_position": 5.0},
            "gripper": {"has_velocity_limits": True, "max_velocity": 3.0},
        },
        "control_rate_hz": 10,
    }))
    audit = tmp_path / "audit.jsonl"
    proc = ServeProcess(["--embodiment", "so100", "--safety-config", str(safety), "--audit-log", str(audit)])
    try:
        data = act(proc, episode_id="clamp-1")
        actions = check_actions(data)
        assert data["guard_clamped"] is True
        assert np.all(np.abs(actions[:, 0]) <= 5.0)
        assert np.all(np.abs(np.diff(actions[:, 5])) <= 3.0 / 10 + 1e-4)
        # Within the limits the guard changes nothing.
        inside = (np.abs(raw[:, 0]) <= 5.0)
        np.testing.assert_array_equal(actions[inside, 0], raw[inside, 0])
        violations = data["guard_violations"]
        assert {v["joint"] for v in violations} <= {"shoulder_pan", "gripper", "shoulder_lift", "elbow_flex",
                                                    "wrist_flex", "wrist_roll"}
        assert any(v["joint"] == "shoulder_pan" and v["limit"] in ("position_min", "position_max")
                   for v in violations)
        last_applied = {(v["step"], v["joint"]): v["applied"] for v in violations}  # a value can pass several checks
        for (step, joint), applied in last_applied.items():
            assert actions[step, SO100_JOINTS.index(joint)] == pytest.approx(applied, abs=1e-4)
        lines = [json.loads(line) for line in audit.read_text().splitlines()]
        assert len(lines) == len(violations)
        for line in lines:
            assert line["request_id"] == data["request_id"] and line["episode_id"] == "clamp-1"
            assert {"time", "joint", "limit", "requested", "applied"} <= set(line)
        m = metrics_of(proc)
        assert metric(m, "tether_guard_clamped_total") == 1
        assert metric(m, "tether_guard_violations_total") == len(violations)
        assert metric(m, "tether_guard_violations_total", joint="shoulder_pan") >= 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_bad_embodiment_files_fail_at_start_naming_the_field(tmp_path):
    bad = tmp_path / "bad.json"
    good = json.loads((REPO / "models" / "embodiments" / "so100.json").read_text())
    good["joints"][2]["max_velocity"] = -1
    bad.write_text(json.dumps(good))
    err = start_fails(["--custom-embodiment-config", str(bad)])
    assert "max_velocity" in err and "joints[2]" in err, err
    safety = tmp_path / "safety.json"
    safety.write_text(json.dumps({"joint_limits": {"shoulder_pan": {"has_position_limits": True,
                                                                    "min_position": 1, "max_positon": 2}}}))
    err = start_fails(["--embodiment", "so100", "--safety-config", str(safety)])
    assert "max_positon" in err, err
    err = start_fails(["--embodiment", "franka"])  # 8 joints, the demo model has 6 action values
    assert "franka" in err and "6" in err, err
    err = start_fails(["--embodiment", "no-such-robot"])
    assert "no-such-robot" in err, err


# -- deadline and injected latency -----------------------------------------------------------------------------


def test_deadline_answers_in_time_with_the_last_good_chunk(plain):
    """Behaviour, not wall-clock bounds: a 504 or a last-good answer can only come from not waiting for the model."""
    expected = check_actions(act(plain, seed=7))
    proc = ServeProcess(["--inject-latency-ms", "600", "--deadline-ms", "150", "--request-timeout-ms", "5000",
                         "--control-rate-hz", "10"])
    try:
        first = post_act(proc, act_body(seed=7, episode_id="slow"))
        expect_error(first, 504, "deadline_exceeded")
        # The late forward pass finishes and becomes the episode's last good chunk; until it has (on a loaded machine
        # that can take a while), the same request is answered 504 again. Every pass uses seed 7, so whichever pass
        # finished first, the last good chunk is the seed-7 chunk.
        misses = 0
        for _ in range(120):
            resp = post_act(proc, act_body(seed=7, episode_id="slow"))
            if resp[0] == 200:
                data = ok_json(resp)
                break
            expect_error(resp, 504, "deadline_exceeded")
            misses += 1
            time.sleep(0.5)
        else:
            raise AssertionError("the late forward pass never became the last good chunk")
        assert data["deadline_exceeded"] is True and data["action_source"] == "last_good"
        assert data["injected_latency_ms"] == 600
        shift = data["advanced_steps"]
        assert shift >= 1, shift  # advanced by the control steps elapsed since that chunk was made
        advanced = np.concatenate([expected[min(shift, CHUNK - 1):], np.repeat(expected[-1:], min(shift, CHUNK - 1), 0)])
        np.testing.assert_allclose(check_actions(data), advanced, rtol=0, atol=1e-4)
        # Another episode has nothing cached.
        expect_error(post_act(proc, act_body(episode_id="other")), 504, "deadline_exceeded")
        m = metrics_of(proc)
        assert metric(m, "tether_deadline_exceeded_total") == 3 + misses
        assert metric(m, "tether_injected_latency_ms") == 600
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_latency_injection_without_deadline_is_reported():
    proc = ServeProcess(["--inject-latency-ms", "200"])
    try:
        t0 = time.monotonic()
        data = act(proc)
        assert time.monotonic() - t0 >= 0.2
        assert data["injected_latency_ms"] == 200 and "deadline_exceeded" not in data
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- adaptive steps ------------------------------------------------------------------------------------------


def test_adaptive_steps(plain):
    full = check_actions(act(plain, seed=11))
    tight = ServeProcess(["--adaptive-steps", "--adaptive-threshold", "1e-9"])
    loose = ServeProcess(["--adaptive-steps", "--adaptive-threshold", "0.9"])
    try:
        data = act(tight, seed=11)
        assert data["denoise_steps_used"] == 10
        np.testing.assert_array_equal(check_actions(data), full)
        data = act(loose, seed=11)
        assert 2 <= data["denoise_steps_used"] < 10
        assert metric(metrics_of(loose), "tether_denoise_steps_total") == data["denoise_steps_used"]
    finally:
        assert tight.stop() == 0 and loose.stop() == 0
    default = ServeProcess(["--adaptive-steps"])
    try:
        assert json.loads(request(default.port, "GET", "/config")[2])["wedges"]["adaptive_threshold"] == pytest.approx(0.05)
        assert 2 <= act(default)["denoise_steps_used"] <= 10
    finally:
        assert default.stop() == 0


# -- similarity skip and episodes ------------------------------------------------------------------------------


def test_similarity_skip_reuses_at_most_k_times_per_episode():
    proc = ServeProcess(["--action-similarity-threshold", "0.01", "--max-similar-skips", "2"])
    try:
        answers = [act(proc, seed=s, episode_id="ep-a") for s in (1, 2, 3, 4)]
        assert [a["action_skipped"] for a in answers] == [False, True, True, False]
        assert [a["action_source"] for a in answers] == ["model", "cache", "cache", "model"]
        assert answers[1]["similarity_distance"] == 0.0
        # The cached chunk advanced by the control steps elapsed (past its end: its last action, held).
        shift = min(answers[1]["advanced_steps"], CHUNK - 1)
        np.testing.assert_array_equal(check_actions(answers[1])[0], check_actions(answers[0])[shift])
        # A changed state is not similar; another episode starts from nothing.
        moved = act(proc, seed=5, episode_id="ep-a", state=[s + 20.0 for s in STATE])
        assert moved["action_skipped"] is False and moved["similarity_distance"] > 0.01
        assert act(proc, seed=6, episode_id="ep-b")["action_skipped"] is False
        assert metric(metrics_of(proc), "tether_action_skip_total") == 2
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_similarity_flags_go_together():
    err = start_fails(["--action-similarity-threshold", "0.1"])
    assert "--max-similar-skips" in err, err


# -- circuit breaker -----------------------------------------------------------------------------------------


def nan_checkpoint(tmp_path: Path) -> Path:
    """A copy of the demo checkpoint whose action output projection holds NaN: it loads, and every chunk it
    produces is NaN."""
    dst = tmp_path / "nan-model"
    shutil.copytree(DEMO, dst)
    path = dst / "model.safetensors"
    data = bytearray(path.read_bytes())
    (header_len,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + header_len])
    name = next(k for k in header if k.endswith("action_out_proj.bias"))
    begin, end = header[name]["data_offsets"]
    assert header[name]["dtype"] == "F32"
    start = 8 + header_len + begin
    data[start:8 + header_len + end] = struct.pack("<f", float("nan")) * ((end - begin) // 4)
    path.write_bytes(bytes(data))
    return dst


def test_breaker_opens_on_a_model_that_produces_nan(tmp_path):
    proc = ServeProcess(["--max-consecutive-crashes", "2"], checkpoint=nan_checkpoint(tmp_path))
    try:
        for _ in range(2):
            err = expect_error(post_act(proc, act_body()), 500, "inference_failed")
            assert "non-finite" in err["message"]
        status, headers, body = post_act(proc, act_body())
        expect_error((status, headers, body), 503, "circuit_open")
        assert headers["retry-after"] == "60"
        status, headers, body = request(proc.port, "GET", "/health")
        health = json.loads(body)
        assert status == 503 and health["state"] == "circuit_open" and health["circuit"]["state"] == "open"
        m = metrics_of(proc)
        assert metric(m, "tether_circuit_open") == 1 and metric(m, "tether_circuit_rejected_total") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_breaker_half_open_probe_closes_it(tmp_path):
    fault = tmp_path / "fail-now"
    proc = ServeProcess(["--max-consecutive-crashes", "3", "--circuit-reset-ms", "1500",
                         "--inject-failure-file", str(fault)])
    try:
        fault.touch()
        for _ in range(3):
            expect_error(post_act(proc, act_body()), 500, "inference_failed")
        status, headers, _ = post_act(proc, act_body())
        assert status == 503 and int(headers["retry-after"]) in (1, 2)
        time.sleep(1.6)
        expect_error(post_act(proc, act_body()), 500, "inference_failed")  # the probe fails: open again
        expect_error(post_act(proc, act_body()), 503, "circuit_open")
        fault.unlink()
        time.sleep(1.6)
        data = act(proc)  # the probe succeeds
        assert data["circuit_state"] == "closed"
        check_actions(data)
        assert proc.wait_ready(5)["state"] == "ready"
        assert metric(metrics_of(proc), "tether_circuit_opened_total") == 2
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- cloud fallback -------------------------------------------------------------------------------------------


def test_cloud_fallback_answers_failures_and_deadline_misses(tmp_path, plain):
    expected = check_actions(act(plain, seed=21))
    fault = tmp_path / "fail-now"
    proc = ServeProcess(["--cloud-fallback", plain.url, "--fallback-timeout-ms", "20000",
                         "--inject-failure-file", str(fault)])
    try:
        fault.touch()
        data = act(proc, seed=21)
        assert data["fallback_used"] is True and data["action_source"] == "fallback"
        np.testing.assert_array_equal(check_actions(data), expected)
        assert "injected failure" in data["inference_error"]
        fault.unlink()
        data = act(proc, seed=21)
        assert data["fallback_used"] is False and data["action_source"] == "model"
        m = metrics_of(proc)
        assert metric(m, "tether_fallback_total", outcome="success") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_unreachable_fallback_is_reported_and_the_error_kept(tmp_path):
    fault = tmp_path / "fail-now"
    proc = ServeProcess(["--cloud-fallback", "http://127.0.0.1:9", "--fallback-timeout-ms", "500",
                         "--inject-failure-file", str(fault)])
    try:
        fault.touch()
        err = expect_error(post_act(proc, act_body()), 500, "inference_failed")
        assert "fallback" in err["message"]
        assert metric(metrics_of(proc), "tether_fallback_total", outcome="failure") == 1
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_fallback_covers_a_deadline_miss(plain):
    proc = ServeProcess(["--cloud-fallback", plain.url, "--deadline-ms", "100", "--inject-latency-ms", "1500",
                         "--fallback-timeout-ms", "20000"])
    try:
        data = act(proc, episode_id="fresh")
        assert data["deadline_exceeded"] is True and data["fallback_used"] is True
        check_actions(data)
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


# -- real-time chunking --------------------------------------------------------------------------------------


def test_rtc_shrinks_the_seam_between_chunks():
    proc = ServeProcess(["--rtc"])
    try:
        first = check_actions(act(proc, seed=31))
        executed, delay = 10, 4
        leftover = first[executed:].tolist()
        plain_next = check_actions(act(proc, seed=32))
        guided = act(proc, seed=32, rtc={"prev_actions": leftover, "inference_delay": delay})
        assert guided["rtc_applied"] is True
        guided_next = check_actions(guided)
        # The seam: where the new chunk takes over from the old one (the first `delay` rows are still the old's).
        seam_plain = np.abs(plain_next[:delay] - first[executed:executed + delay]).max()
        seam_rtc = np.abs(guided_next[:delay] - first[executed:executed + delay]).max()
        assert seam_rtc < 0.5 * seam_plain, (seam_rtc, seam_plain)
        expect_error(post_act(proc, act_body(rtc={"prev_actions": [[0.0] * 5]})), 400, "invalid_field")
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_rtc_needs_the_flag(plain):
    err = expect_error(post_act(plain, act_body(rtc={"prev_actions": [[0.0] * 6], "inference_delay": 1})), 400,
                       "invalid_field")
    assert "--rtc" in err["message"]


# -- trace recording -----------------------------------------------------------------------------------------


def traces(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(binary_path()), "traces", *args], capture_output=True, text=True, timeout=60)


def test_record_traces_and_verify(tmp_path):
    record = tmp_path / "traces"
    proc = ServeProcess(["--record", str(record), "--record-max-bytes", "8192", "--embodiment", "so100"])
    try:
        for i in range(6):
            act(proc, seed=i, episode_id="rec", instruction=f"task {i % 2}")
        expect_error(post_act(proc, act_body(state=[1.0])), 400, "invalid_state")
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
    files = sorted(record.glob("trace-*.jsonl"))
    assert len(files) >= 2, files  # rotated by size
    lines = [json.loads(line) for f in files for line in f.read_text().splitlines()]
    assert len(lines) == 7
    assert [l["seq"] for l in lines] == list(range(lines[0]["seq"], lines[0]["seq"] + 7))
    ok = lines[0]
    assert ok["status"] == "success" and ok["episode_id"] == "rec" and ok["task"] == "task 0"
    assert ok["model"] == "smolvla-demo" and ok["model_hash"].startswith("sha256:")
    assert len(ok["actions"]) == CHUNK and ok["latency_ms"]["total"] > 0
    image = next(iter(ok["inputs"]["images"].values()))
    assert len(image["sha256"]) == 64 and "data" not in image
    assert "guard_clamped" in ok["wedges"]
    bad = lines[-1]
    assert bad["status"] == "failed" and bad["error"]["code"] == "invalid_state" and bad["http_status"] == 400

    verify = traces("verify", "--dir", str(record))
    assert verify.returncode == 0, verify.stdout + verify.stderr
    # Alter the second record: verify reports the break at the line after it.
    target = next(f for f in files if '"seq":%d,' % (lines[0]["seq"] + 1) in f.read_text())
    target.write_text(target.read_text().replace('"task 1"', '"task X"', 1))
    verify = traces("verify", "--dir", str(record))
    assert verify.returncode == 1 and "altered" in verify.stdout, verify.stdout + verify.stderr

    summary = traces("summary", "--dir", str(record), "--by", "task", "--output", str(tmp_path / "s.json"))
    assert summary.returncode == 0, summary.stderr
    groups = json.loads((tmp_path / "s.json").read_text())
    assert groups


def test_record_images_full_replays(tmp_path, plain):
    record = tmp_path / "traces"
    proc = ServeProcess(["--record", str(record), "--record-images", "full"])
    try:
        data = act(proc, seed=5)
    finally:
        assert proc.stop() == 0, proc.stderr_tail()
    line = json.loads(next(record.glob("trace-*.jsonl")).read_text().splitlines()[0])
    images = {cam: img["data"] for cam, img in line["inputs"]["images"].items()}
    replay = ok_json(post_act(plain, json.dumps({"instruction": line["task"], "state": line["inputs"]["state"],
                                                 "images": images, "seed": line["inputs"]["seed"]}).encode()))
    np.testing.assert_array_equal(check_actions(replay), check_actions(data))


# -- exports and tether go -----------------------------------------------------------------------------------


def test_an_export_carries_its_embodiment_to_serve(tmp_path):
    out = tmp_path / "export"
    done = subprocess.run([str(binary_path()), "export", str(DEMO), "-o", str(out), "--embodiment", "so100"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    proc = ServeProcess(["--audit-log", str(tmp_path / "audit.jsonl")], checkpoint=out)
    try:
        data = act(proc)
        assert data["joint_names"] == SO100_JOINTS and "guard_clamped" in data
        assert "embodiment 'so100'" in proc.stderr_tail()
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def test_go_takes_the_wedge_flags():
    help_text = subprocess.run([str(binary_path()), "go", "--help"], capture_output=True, text=True).stdout
    for flag in ("--embodiment", "--safety-config", "--deadline-ms", "--adaptive-steps", "--max-similar-skips",
                 "--max-consecutive-crashes", "--cloud-fallback", "--inject-latency-ms", "--rtc", "--record"):
        assert flag in help_text, flag
