"""Shared fixtures: a scripted in-process HTTP server standing in for `tether serve` in the client's unit tests."""

from __future__ import annotations

import json
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Dict, List, Optional

import pytest

ACT_OK = {
    "actions": [[0.5 * i + j for j in range(6)] for i in range(50)],
    "num_actions": 50,
    "action_dim": 6,
    "latency_ms": {
        "total": 12.5,
        "queue": 0.1,
        "preprocess": 1.0,
        "vision": 2.0,
        "prefix": 3.0,
        "denoise": 6.0,
        "postprocess": 0.4,
    },
    "inference_mode": {"backend": "cpu", "precision": "fp32", "gemm": "onednn"},
    "model_hash": "sha256:" + "ab" * 32,
    "request_id": "generated-1",
    "episode_id": None,
    "batch_size": 1,
    "warnings": [],
}


class Reply:
    """One scripted answer. ``delay`` sleeps before answering; ``drop`` closes the connection after answering
    without saying so (an idle keep-alive timeout); ``early`` answers before reading the body, then half-closes
    and drains it (what a careful server does for 413)."""

    def __init__(
        self,
        status: int = 200,
        body: Any = None,
        headers: Optional[Dict[str, str]] = None,
        delay: float = 0.0,
        drop: bool = False,
        early: bool = False,
    ) -> None:
        self.status = status
        self.body = ACT_OK if body is None and status == 200 else body
        self.headers = headers or {}
        self.delay = delay
        self.drop = drop
        self.early = early


def error_reply(status: int, code: str, message: str = "bad", **kw: Any) -> Reply:
    return Reply(status, {"error": {"code": code, "message": message}}, **kw)


class Recorded:
    def __init__(self, method: str, path: str, headers: Dict[str, str], body: bytes, port: int) -> None:
        self.method = method
        self.path = path
        self.headers = headers
        self.body = body
        self.port = port  # the client's source port: equal ports mean one keep-alive connection

    def json(self) -> Any:
        """The body decoded as the client sent it: msgpack (the client's default) or JSON."""
        if self.headers.get("content-type") == "application/msgpack":
            import msgpack

            return msgpack.unpackb(self.body, raw=False)
        return json.loads(self.body)


class FakeServer:
    def __init__(self) -> None:
        self.script: List[Reply] = []
        self.default = Reply()
        self.requests: List[Recorded] = []
        self.lock = threading.Lock()
        fake = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args: Any) -> None:
                pass

            def setup(self) -> None:
                super().setup()
                # Headers and body go out in two writes; without this, Nagle + delayed ACK add 40 ms each.
                self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

            def _handle(self) -> None:
                with fake.lock:
                    reply = fake.script.pop(0) if fake.script else fake.default
                length = int(self.headers.get("Content-Length") or 0)
                body = b""
                if not reply.early:
                    body = self.rfile.read(length) if length else b""
                with fake.lock:
                    fake.requests.append(
                        Recorded(
                            self.command,
                            self.path,
                            {k.lower(): v for k, v in self.headers.items()},
                            body,
                            self.client_address[1],
                        )
                    )
                if reply.delay:
                    time.sleep(reply.delay)
                if isinstance(reply.body, (dict, list)):
                    payload = json.dumps(reply.body).encode()
                    ctype = "application/json"
                elif isinstance(reply.body, bytes):
                    payload, ctype = reply.body, "text/plain"
                else:
                    payload, ctype = (reply.body or "").encode(), "text/plain"
                ctype = reply.headers.get("Content-Type", ctype)
                self.send_response(reply.status)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(payload)))
                rid = self.headers.get("X-Tether-Request-ID") or "srv-" + str(len(fake.requests))
                self.send_header("X-Tether-Request-ID", rid)
                for k, v in reply.headers.items():
                    if k != "Content-Type":
                        self.send_header(k, v)
                if reply.early:
                    self.send_header("Connection", "close")
                self.end_headers()
                self.wfile.write(payload)
                self.wfile.flush()
                if reply.early:
                    self.connection.shutdown(socket.SHUT_WR)
                    self.connection.settimeout(2.0)
                    try:
                        while self.connection.recv(1 << 16):
                            pass
                    except OSError:
                        pass
                    self.close_connection = True
                if reply.drop:
                    self.close_connection = True

            do_GET = _handle
            do_POST = _handle
            do_PUT = _handle

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.thread = threading.Thread(
            target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
        )
        self.thread.start()

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def fake() -> Any:
    server = FakeServer()
    yield server
    server.stop()
