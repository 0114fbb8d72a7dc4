#!/usr/bin/env python3
"""The same load on every transport of one `tether serve`: throughput, p50 and p99 per transport at 1 and 16 clients,
against the engine's own latency (`tether bench` on the same checkpoint) measured in the same run.

Usage: .venv/bin/python bench/transport_load.py [--checkpoint models/demo/smolvla-demo] [--clients 1,16]
                                                [--requests 200] [--transports http,kserve,openpi,gr00t,zmq]

Each client is its own process holding one connection (the real client library where one exists: openpi-client's
WebsocketClientPolicy, tritonclient's InferenceServerClient, Tether's TetherClient over ZMQ; a REQ socket written from
the protocol for GR00T; a keep-alive http.client for /act). Every request carries the same 224x224 RGB frame as raw
uint8 pixels (no image codec on either side), the same state and instruction, and its own seed. The server runs with
--batch-timeout-ms 0, so a lone client never waits for company and 16 clients batch what queued. Latency is measured
at the client, from the call to its return, and includes the client library's own encoding and decoding.
"""

from __future__ import annotations

import argparse
import base64
import http.client
import json
import multiprocessing as mp
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))

INSTRUCTION = "pick up the cube"


def frame() -> np.ndarray:
    y, x = np.mgrid[0:224, 0:224]
    return np.stack([x % 256, y % 256, (x + y) % 256], axis=-1).astype(np.uint8)


def make_client(transport: str, host: str, ports: Dict[str, int], camera: str, state: List[float]) -> Callable[[int], None]:
    img = frame()
    st = np.asarray(state, np.float32)
    if transport == "http":
        conn = http.client.HTTPConnection(host, ports["http"], timeout=60)
        raw = {"data": base64.b64encode(img.tobytes()).decode(), "shape": list(img.shape)}

        def act(seed: int) -> None:
            body = json.dumps({"instruction": INSTRUCTION, "state": state, "images": {camera: raw}, "seed": seed})
            conn.request("POST", "/act", body, {"Content-Type": "application/json"})
            r = conn.getresponse()
            data = r.read()
            if r.status != 200:
                raise RuntimeError(f"/act {r.status}: {data[:200]!r}")
        return act
    if transport == "kserve":
        import tritonclient.http as triton
        client = triton.InferenceServerClient(f"{host}:{ports['http']}", network_timeout=60)
        name = client.get_server_metadata()  # warms the connection
        model = ports["model_name"]

        def act(seed: int) -> None:
            inputs = [triton.InferInput("instruction", [1], "BYTES"), triton.InferInput("state", [1, len(st)], "FP32"),
                      triton.InferInput(f"image.{camera}", [1, *img.shape], "UINT8"), triton.InferInput("seed", [1], "INT64")]
            inputs[0].set_data_from_numpy(np.array([INSTRUCTION.encode()], dtype=np.object_))
            inputs[1].set_data_from_numpy(st[None])
            inputs[2].set_data_from_numpy(img[None])
            inputs[3].set_data_from_numpy(np.array([seed], np.int64))
            result = client.infer(model, inputs, outputs=[triton.InferRequestedOutput("actions")])
            result.as_numpy("actions")
        del name
        return act
    if transport == "openpi":
        from openpi_client import websocket_client_policy
        policy = websocket_client_policy.WebsocketClientPolicy(host, ports["openpi"])

        def act(seed: int) -> None:
            del seed  # openpi's protocol has no seed: the server derives one per request
            policy.infer({"observation/image": img, "observation/state": st, "prompt": INSTRUCTION})
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

        def act(seed: int) -> None:
            obs = {"video": {camera: npy(img[None, None])}, "state": {"state": npy(st[None, None])},
                   "language": {"task": [[INSTRUCTION]]}}
            sock.send(msgpack.packb({"endpoint": "get_action", "data": {"observation": obs, "options": {"seed": seed}}}))
            reply = msgpack.unpackb(sock.recv())
            if isinstance(reply, dict) and "error" in reply:
                raise RuntimeError(reply["error"])
        return act
    if transport == "zmq":
        from tether_client import TetherClient
        client = TetherClient(f"http://{host}:{ports['http']}", transport="zmq", zmq_url=f"tcp://{host}:{ports['zmq']}")

        def act(seed: int) -> None:
            client.act(img, state=state, instruction=INSTRUCTION, seed=seed)
        return act
    raise SystemExit(f"unknown transport {transport}")


def client_process(args) -> List[float]:
    transport, host, ports, camera, state, requests, index, barrier = args
    act = make_client(transport, host, ports, camera, state)
    act(index * 100000)  # connection set-up and first request: not timed
    barrier.wait()
    times = []
    for i in range(requests):
        t0 = time.perf_counter()
        act(index * 100000 + i + 1)
        times.append((time.perf_counter() - t0) * 1000)
    return times


def engine_latency(binary: Path, checkpoint: str) -> float:
    out = subprocess.run([str(binary), "bench", checkpoint, "--iterations", "100", "--json"], check=True,
                         capture_output=True, text=True).stdout
    j = json.loads(out)
    for key in ("p50_ms", "latency_p50_ms"):
        if key in j:
            return float(j[key])
    return float(j["latency_ms"]["p50"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=str(REPO / "models/demo/smolvla-demo"))
    ap.add_argument("--clients", default="1,16")
    ap.add_argument("--requests", type=int, default=200, help="requests per client at 1 client (divided at more)")
    ap.add_argument("--transports", default="http,kserve,openpi,gr00t,zmq")
    ap.add_argument("--binary", default=str(REPO / "build/release/tether"))
    a = ap.parse_args()
    binary = Path(a.binary)
    transports = a.transports.split(",")
    clients = [int(c) for c in a.clients.split(",")]

    engine_p50 = engine_latency(binary, a.checkpoint)
    cmd = [str(binary), "serve", a.checkpoint, "--port", "0", "--batch-timeout-ms", "0", "--max-batch", "16",
           "--openpi-port", "0", "--gr00t-port", "0", "--zmq-port", "0", "--model-name", "demo"]
    server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
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

        cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
        print(f"checkpoint {a.checkpoint}; CPU {cpu}, {os.cpu_count()} cores; engine alone (tether bench, batch 1): "
              f"p50 {engine_p50:.2f} ms")
        print("| transport | clients | requests | throughput (req/s) | p50 (ms) | p99 (ms) | p50 over engine (ms) |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for transport in transports:
            for n in clients:
                per_client = max(10, a.requests // n)
                with mp.Manager() as manager:
                    barrier = manager.Barrier(n)
                    with mp.Pool(n) as pool:
                        t0 = time.perf_counter()
                        results = pool.map(client_process, [(transport, host, ports, camera, state, per_client, i,
                                                             barrier) for i in range(n)])
                        wall = time.perf_counter() - t0
                lat = np.array([t for r in results for t in r])
                # Throughput over the timed part: requests / the slowest client's total.
                span = max(sum(r) for r in results) / 1000
                p50, p99 = np.percentile(lat, 50), np.percentile(lat, 99)
                print(f"| {transport} | {n} | {lat.size} | {lat.size / span:.1f} | {p50:.2f} | {p99:.2f} | "
                      f"{p50 - engine_p50:+.2f} |", flush=True)
                del wall
    finally:
        server.terminate()
        server.wait(timeout=30)


if __name__ == "__main__":
    main()
