"""Clients for the tests of the two ZMQ transports (`--gr00t-port`, `--zmq-port`): sockets set up one way, a client
written from Isaac-GR00T's PolicyClient protocol, a DEALER speaking Tether's msgpack /act, and what both read back
from a server (metrics, trace lines). Imported after the test modules' importorskip of msgpack and zmq."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence

import msgpack
import numpy as np
import zmq

from serve_process import SAMPLE_PNG, ServeProcess, parse_metrics, request
from test_serve_integration import STATE

PNG = SAMPLE_PNG.read_bytes()


def connect(kind: int, port: int, timeout_ms: int = 30000, server_key: Optional[bytes] = None,
            host: str = "127.0.0.1") -> zmq.Socket:
    """A socket of `kind` connected to the server: no linger on close, receives time out (zmq.Again)."""
    socket = zmq.Context.instance().socket(kind)
    socket.setsockopt(zmq.LINGER, 0)
    socket.setsockopt(zmq.RCVTIMEO, timeout_ms)
    if server_key:  # CURVE, with a key pair of the client's own
        socket.curve_publickey, socket.curve_secretkey = zmq.curve_keypair()
        socket.curve_serverkey = server_key
    socket.connect(f"tcp://{host}:{port}")
    return socket


@contextlib.contextmanager
def served(args: Sequence[str], env: Optional[Mapping[str, str]] = None) -> Iterator[ServeProcess]:
    """A `tether serve` with `args` for the block; it must exit 0 on SIGTERM afterwards."""
    proc = ServeProcess(list(args), env=env)
    try:
        yield proc
    finally:
        assert proc.stop() == 0, proc.stderr_tail()


def metrics_of(server: ServeProcess) -> Dict:
    return parse_metrics(request(server.port, "GET", "/metrics")[2].decode())


def trace_lines(record_dir: Path) -> List[Dict[str, Any]]:
    return [json.loads(line) for f in sorted(record_dir.glob("trace-*.jsonl")) for line in f.read_text().splitlines()]


class _Client:
    """A client owning one socket; `with client:` closes it at the end of the block."""

    socket: zmq.Socket

    def close(self) -> None:
        self.socket.close(0)

    def __enter__(self):
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# -- GR00T: msgpack with numpy arrays as {"__ndarray_class__": True, "as_npy": <.npy bytes>} ---------------------


def _encode(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        out = io.BytesIO()
        np.save(out, obj, allow_pickle=False)
        return {"__ndarray_class__": True, "as_npy": out.getvalue()}
    return obj


def _decode(obj: Any) -> Any:
    if isinstance(obj, dict) and "__ndarray_class__" in obj:
        return np.load(io.BytesIO(obj["as_npy"]), allow_pickle=False)
    if isinstance(obj, dict) and "__ModalityConfig_class__" in obj:
        return dict(obj["as_json"])
    return obj


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, default=_encode)


def unpack(data: bytes) -> Any:
    return msgpack.unpackb(data, object_hook=_decode)


class Gr00tClient(_Client):
    """PolicyClient's wire behaviour: one REQ socket, one request and one reply at a time."""

    def __init__(self, port: int, api_token: Optional[str] = None, timeout_ms: int = 30000,
                 host: str = "127.0.0.1") -> None:
        self.socket = connect(zmq.REQ, port, timeout_ms, host=host)
        self.api_token = api_token

    def call(self, endpoint: str, data: Optional[Dict[str, Any]] = None, requires_input: bool = True) -> Any:
        req: Dict[str, Any] = {"endpoint": endpoint}
        if requires_input:
            req["data"] = data
        if self.api_token:
            req["api_token"] = self.api_token
        self.socket.send(pack(req))
        return unpack(self.socket.recv())

    def get_action(self, observation: Dict[str, Any], options: Optional[Dict[str, Any]] = None) -> Any:
        return self.call("get_action", {"observation": observation, "options": options})


# -- Tether ZMQ: a msgpack map with /act's fields ----------------------------------------------------------------


def act_msg(**fields: Any) -> Dict[str, Any]:
    """The demo's /act request as a Tether ZMQ message; a field set to None is left out."""
    msg: Dict[str, Any] = {"instruction": "pick up the red cube", "state": STATE, "image": PNG, "seed": 7}
    msg.update(fields)
    return {k: v for k, v in msg.items() if v is not None}


class Dealer(_Client):
    """A DEALER socket: requests may be pipelined, replies are matched by `id`."""

    def __init__(self, port: int, server_key: Optional[bytes] = None, timeout_ms: int = 30000,
                 host: str = "127.0.0.1") -> None:
        self.socket = connect(zmq.DEALER, port, timeout_ms, server_key, host)

    def send(self, msg: Dict[str, Any]) -> None:
        self.socket.send(msgpack.packb(msg))

    def recv(self) -> Dict[str, Any]:
        return msgpack.unpackb(self.socket.recv_multipart()[-1])

    def act(self, **fields: Any) -> Dict[str, Any]:
        self.send(act_msg(**fields))
        return self.recv()
