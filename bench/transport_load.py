#!/usr/bin/env python3
"""The same load on every transport of one `tether serve`: throughput, p50 and p99 per transport at 1 and 16 clients,
against the engine's own latency on the same input, measured in the same run.

Usage: .venv/bin/python bench/transport_load.py [--checkpoint models/demo/smolvla-demo] [--clients 1,16]
                                                [--requests 200] [--transports http,http-json,kserve,openpi,gr00t,zmq]

Each client is its own process holding one connection, with the real client library where one exists: Tether's
TetherClient over HTTP (`http`: msgpack body, raw image bytes) and over ZMQ (`zmq`), openpi-client's
WebsocketClientPolicy, tritonclient's InferenceServerClient; a REQ socket written from the protocol for GR00T, and for
`http-json` a keep-alive http.client (with TCP_NODELAY, as curl) sending the JSON body with the frame in base64, as a
client without msgpack would. Every request carries the same 224x224 RGB frame as raw uint8 pixels (no image codec on
either side), the same state and instruction, and its own seed. The server runs with --batch-timeout-ms 0, so a lone
client never waits for company and 16 clients batch what queued. Latency is measured at the client, from the call to
its return, and includes the client library's own encoding and decoding.

The engine baseline is `tether bench` (Policy::predict at batch 1, nothing else) on the very pixels the transports send:
the frame is written to a PNG (lossless) that bench decodes once, before its timed runs, so every timed run starts from
the same 224x224 RGB image a transport hands to the engine, with the same state and instruction. It is taken right
before and right after each transport's 1-client run, and the mean of the two is the baseline, so a change in the
machine's load between transports hits both sides. "p50 over engine" is everything the server and the client add: the
client library, the wire, the server's decoding and encoding, the batcher's hand-off to the inference thread, the
wedges and the metrics. Every transport's reply carries the server's own timing of the request (/act's latency_ms,
KServe's response parameters, GR00T's info): "server p50" is from its first byte read to its answer, "predict p50" the
forward pass alone, timed as `tether bench` times it. "p50 over own predict" subtracts each request's own forward pass
from its client latency: the same overhead, measured within one request, so it does not move when the machine's speed
drifts between the baseline runs and the load (shared VMs drift by tens of percent over minutes). At 16 clients it
also holds the wait behind other clients' batches.
"""

from __future__ import annotations

import argparse
import base64
import http.client
import json
import multiprocessing as mp
import os
import re
import socket
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path
from typing import Callable, Dict, List, Tuple

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))

INSTRUCTION = "pick up the cube"


def frame() -> np.ndarray:
    y, x = np.mgrid[0:224, 0:224]
    return np.stack([x % 256, y % 256, (x + y) % 256], axis=-1).astype(np.uint8)


def write_png(path: Path, rgb: np.ndarray) -> None:
    """An 8-bit RGB PNG of `rgb`, lossless, so `tether bench` decodes exactly these pixels."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    h, w, _ = rgb.shape
    rows = b"".join(b"\x00" + rgb[y].tobytes() for y in range(h))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)) +
                     chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


# Each act() returns the server's own total for the request (ms) when the reply carries it, else None.
Timing = Tuple[float, float]  # the server's (total, predict) ms for one request, from its reply


def timing_of(latency: dict) -> Timing:
    """/act's latency_ms (total: the server's time for the request; predict: the forward pass, as `tether bench`)."""
    return float(latency["total"]), float(latency["predict"])


def make_client(transport: str, host: str, ports: Dict[str, int], camera: str,
                state: List[float]) -> Callable[[int], Timing]:
    img = frame()
    st = np.asarray(state, np.float32)
    if transport == "http":
        from tether_client import TetherClient
        client = TetherClient(f"http://{host}:{ports['http']}", api_key="", timeout=60, body_format="msgpack")

        def act(seed: int) -> Timing:
            return timing_of(client.act(images={camera: img}, state=state, instruction=INSTRUCTION, seed=seed).latency_ms)
        return act
    if transport == "http-json":
        conn = http.client.HTTPConnection(host, ports["http"], timeout=60)
        conn.connect()
        conn.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        raw = {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}

        def act(seed: int) -> Timing:
            body = json.dumps({"instruction": INSTRUCTION, "state": state, "images": {camera: raw}, "seed": seed})
            conn.request("POST", "/act", body, {"Content-Type": "application/json"})
            r = conn.getresponse()
            data = r.read()
            if r.status != 200:
                raise RuntimeError(f"/act {r.status}: {data[:200]!r}")
            return timing_of(json.loads(data)["latency_ms"])
        return act
    if transport == "kserve":
        import tritonclient.http as triton
        client = triton.InferenceServerClient(f"{host}:{ports['http']}", network_timeout=60)
        name = client.get_server_metadata()  # warms the connection
        model = ports["model_name"]

        def act(seed: int) -> Timing:
            inputs = [triton.InferInput("instruction", [1], "BYTES"), triton.InferInput("state", [1, len(st)], "FP32"),
                      triton.InferInput(f"image.{camera}", [1, *img.shape], "UINT8"), triton.InferInput("seed", [1], "INT64")]
            inputs[0].set_data_from_numpy(np.array([INSTRUCTION.encode()], dtype=np.object_))
            inputs[1].set_data_from_numpy(st[None])
            inputs[2].set_data_from_numpy(img[None])
            inputs[3].set_data_from_numpy(np.array([seed], np.int64))
            result = client.infer(model, inputs, outputs=[triton.InferRequestedOutput("actions")])
            result.as_numpy("actions")
            params = result.get_response()["parameters"]
            return float(params["tether_total_ms"]), float(params["tether_predict_ms"])
        del name
        return act
    if transport == "openpi":
        from openpi_client import websocket_client_policy
        policy = websocket_client_policy.WebsocketClientPolicy(host, ports["openpi"])

        def act(seed: int) -> Timing:
            del seed  # openpi's protocol has no seed: the server derives one per request
            reply = policy.infer({"observation/image": img, "observation/state": st, "prompt": INSTRUCTION})
            return timing_of(reply["tether"]["latency_ms"])
        return act
    if transport == "gr00t":
        import msgpack
        import zmq
        sock = zmq.Context.instance().socket(zmq.REQ)
        sock.connect(f"tcp://{host}:{ports['gr00t']}")

        def npy(a: np.ndarray) -> dict:
            import io
            buf = io.BytesIO()
            np.save(buf, a, allow_pickle=False)
            return {"__ndarray_class__": True, "as_npy": buf.getvalue()}

        def act(seed: int) -> Timing:
            obs = {"video": {camera: npy(img[None, None])}, "state": {"state": npy(st[None, None])},
                   "language": {"task": [[INSTRUCTION]]}}
            sock.send(msgpack.packb({"endpoint": "get_action", "data": {"observation": obs, "options": {"seed": seed}}}))
            reply = msgpack.unpackb(sock.recv())
            if isinstance(reply, dict) and "error" in reply:
                raise RuntimeError(reply["error"])
            return timing_of(reply[1]["tether"][0]["latency_ms"])
        return act
    if transport == "zmq":
        from tether_client import TetherClient
        client = TetherClient(f"http://{host}:{ports['http']}", transport="zmq", zmq_url=f"tcp://{host}:{ports['zmq']}")

        def act(seed: int) -> Timing:
            return timing_of(client.act(img, state=state, instruction=INSTRUCTION, seed=seed).latency_ms)
        return act
    raise SystemExit(f"unknown transport {transport}")


def client_process(args) -> Tuple[List[float], List[Tuple[float, float]]]:
    transport, host, ports, camera, state, requests, index, barrier = args
    act = make_client(transport, host, ports, camera, state)
    for warm in range(3):  # connection set-up and first requests: not timed
        act(index * 100000 + 90000 + warm)
    barrier.wait()
    times, server = [], []
    for i in range(requests):
        t0 = time.perf_counter()
        timing = act(index * 100000 + i + 1)
        times.append((time.perf_counter() - t0) * 1000)
        server.append(timing)
    return times, server


def engine_latency(binary: Path, checkpoint: str, camera: str, png: Path, state: List[float]) -> float:
    """p50 of `tether bench` on the transports' frame, state and instruction (the PNG is decoded before timing)."""
    out = subprocess.run([str(binary), "bench", checkpoint, "--iterations", "100", "--json",
                          "--image", f"{camera}={png}", "--state=" + ",".join(str(v) for v in state),
                          "--instruction", INSTRUCTION], check=True, capture_output=True, text=True).stdout
    return float(json.loads(out)["latency_ms"]["p50"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=str(REPO / "models/demo/smolvla-demo"))
    ap.add_argument("--clients", default="1,16")
    ap.add_argument("--requests", type=int, default=200, help="requests per client at 1 client (divided at more)")
    ap.add_argument("--transports", default="http,http-json,kserve,openpi,gr00t,zmq")
    ap.add_argument("--binary", default=str(REPO / "build/release/tether"))
    a = ap.parse_args()
    binary = Path(a.binary)
    transports = a.transports.split(",")
    clients = [int(c) for c in a.clients.split(",")]

    cmd = [str(binary), "serve", a.checkpoint, "--port", "0", "--batch-timeout-ms", "0", "--max-batch", "16",
           "--openpi-port", "0", "--gr00t-port", "0", "--zmq-port", "0", "--model-name", "demo"]
    server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    scratch = tempfile.TemporaryDirectory(prefix="tether_transport_load_")
    try:
        ports: Dict[str, int] = {"model_name": "demo"}  # type: ignore[dict-item]
        host = "127.0.0.1"
        assert server.stdout is not None
        for line in server.stdout:
            m = re.match(r"tether serve: (\S+) listening on \S+:(\d+)", line)
            if m:
                ports[m.group(1)] = int(m.group(2))
            m = re.match(r"tether serve: listening on http://(\S+):(\d+)", line)
            if m:
                host, ports["http"] = m.group(1), int(m.group(2))
                break
        for _ in range(600):
            try:
                c = http.client.HTTPConnection(host, ports["http"], timeout=2)
                c.request("GET", "/health")
                if c.getresponse().status == 200:
                    break
            except OSError:
                pass
            time.sleep(0.1)
        c = http.client.HTTPConnection(host, ports["http"], timeout=5)
        c.request("GET", "/config")
        config = json.loads(c.getresponse().read())
        camera = config["cameras"][0].replace("observation.images.", "")
        state = [0.0] * int(config["state_dim"])

        png = Path(scratch.name) / "frame.png"
        write_png(png, frame())

        cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
        print(f"checkpoint {a.checkpoint}; CPU {cpu}, {os.cpu_count()} cores")
        print("| transport | clients | requests | throughput (req/s) | p50 (ms) | p99 (ms) | engine p50 (ms) | "
              "p50 over engine (ms) | server p50 (ms) | predict p50 (ms) | p50 over own predict (ms) |")
        print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for transport in transports:
            engine_before = engine_latency(binary, a.checkpoint, camera, png, state)
            engine_p50 = engine_before
            for n in clients:
                per_client = max(10, a.requests // n)
                with mp.Manager() as manager:
                    barrier = manager.Barrier(n)
                    with mp.Pool(n) as pool:
                        t0 = time.perf_counter()
                        results = pool.map(client_process, [(transport, host, ports, camera, state, per_client, i,
                                                             barrier) for i in range(n)])
                        wall = time.perf_counter() - t0
                if n == clients[0]:  # the engine again right after: the baseline is the mean of both sides
                    engine_p50 = (engine_before + engine_latency(binary, a.checkpoint, camera, png, state)) / 2
                lat = np.array([t for r, _ in results for t in r])
                timings = np.array([t for _, s in results for t in s])  # (total, predict) per request
                # Per request: the client's latency minus that very request's forward pass. Unlike the p50 over the
                # engine baseline it does not move when the machine's speed drifts between the two measurements.
                over_own = lat - timings[:, 1]
                # Throughput over the timed part: requests / the slowest client's total.
                span = max(sum(r) for r, _ in results) / 1000
                p50, p99 = np.percentile(lat, 50), np.percentile(lat, 99)
                print(f"| {transport} | {n} | {lat.size} | {lat.size / span:.1f} | {p50:.2f} | {p99:.2f} | "
                      f"{engine_p50:.2f} | {p50 - engine_p50:+.2f} | {np.percentile(timings[:, 0], 50):.2f} | "
                      f"{np.percentile(timings[:, 1], 50):.2f} | {np.percentile(over_own, 50):+.2f} |", flush=True)
                del wall
    finally:
        server.terminate()
        server.wait(timeout=30)
        scratch.cleanup()


if __name__ == "__main__":
    main()
