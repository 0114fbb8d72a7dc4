"""Starts the real `tether serve` binary for the integration tests and talks raw HTTP to it."""

from __future__ import annotations

import atexit
import http.client
import json
import os
import queue
import re
import signal
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Tuple

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "models" / "demo" / "smolvla-demo"
SAMPLE_PNG = REPO / "models" / "demo" / "sample.png"
FIXTURE_IMAGES = REPO / "tests" / "fixtures" / "vision"
LISTENING = re.compile(r"^tether serve: listening on http://(\S+):(\d+)\s*$")
# Printed before the HTTP line, one per transport besides HTTP (openpi, gr00t, zmq).
TRANSPORT_LISTENING = re.compile(r"^tether serve: (\S+) listening on (\S+):(\d+)\s*$")


_RUNNING: "set[ServeProcess]" = set()


@atexit.register
def _kill_leftovers() -> None:
    # An interrupted test run must not leave servers behind.
    for proc in list(_RUNNING):
        proc.kill()


def binary_path() -> Path:
    path = Path(os.environ.get("TETHER_BINARY", "build/release/tether"))
    return path if path.is_absolute() else REPO / path


def hub_cache_holding(hub: Path, repo_id: str, snapshot: Path) -> Path:
    """Lays out `hub` as a Hugging Face hub cache whose `repo_id` (main) is the directory `snapshot`; returns `hub`.
    A checkpoint naming a repository the hub cannot serve here (e.g. GR00T N1.6's Eagle directory) finds it there."""
    repo = hub / ("models--" + repo_id.replace("/", "--"))
    (repo / "snapshots").mkdir(parents=True)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("main")
    (repo / "snapshots" / "main").symlink_to(snapshot)
    return hub


class ServeProcess:
    """One `tether serve` child. Reads the port from the `listening on` line; :meth:`stop` sends SIGTERM."""

    def __init__(
        self,
        args: Sequence[str] = (),
        env: Optional[Mapping[str, str]] = None,
        checkpoint: Path = DEMO,
        wait_ready: bool = True,
        start_timeout: float = 60.0,
        command: Optional[Sequence[str]] = None,
    ) -> None:
        # `command`: another verb that ends up serving (`go --model ...`), instead of `serve <checkpoint>`.
        self.cmd = ([str(binary_path()), *command, "--port", "0", *args] if command is not None
                    else [str(binary_path()), "serve", str(checkpoint), "--port", "0", *args])
        full_env = dict(os.environ)
        full_env.pop("TETHER_API_KEY", None)
        if env:
            full_env.update(env)
        self.stderr_file = tempfile.TemporaryFile(mode="w+b")
        self.proc = subprocess.Popen(
            self.cmd, stdout=subprocess.PIPE, stderr=self.stderr_file, stdin=subprocess.DEVNULL, env=full_env
        )
        _RUNNING.add(self)
        self.stdout_lines: "queue.Queue[Optional[str]]" = queue.Queue()
        self.stdout_seen: List[str] = []
        self.transport_ports: Dict[str, int] = {}  # transport name -> bound port
        threading.Thread(target=self._drain_stdout, daemon=True).start()
        self.host, self.port = self._wait_listening(start_timeout)
        self.url = f"http://{self.host}:{self.port}"
        if wait_ready:
            self.wait_ready(start_timeout)

    def _drain_stdout(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            self.stdout_lines.put(raw.decode("utf-8", "replace"))
        self.stdout_lines.put(None)

    def stderr_tail(self, n: int = 3000) -> str:
        self.stderr_file.flush()
        self.stderr_file.seek(0)
        return self.stderr_file.read().decode("utf-8", "replace")[-n:]

    def _wait_listening(self, timeout: float) -> Tuple[str, int]:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.kill()
                raise AssertionError(f"no 'listening on' line within {timeout} s from {self.cmd}: {self.stderr_tail()}")
            try:
                line = self.stdout_lines.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                rc = self.proc.wait(timeout=10)
                raise AssertionError(f"{self.cmd} exited with {rc} before listening; stderr: {self.stderr_tail()}")
            self.stdout_seen.append(line)
            t = TRANSPORT_LISTENING.match(line)
            if t:
                self.transport_ports[t.group(1)] = int(t.group(3))
                continue
            m = LISTENING.match(line)
            if m:
                return m.group(1), int(m.group(2))

    def wait_ready(self, timeout: float = 60.0) -> Dict[str, Any]:
        deadline = time.monotonic() + timeout
        last: Any = None
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise AssertionError(f"server exited with {self.proc.returncode}: {self.stderr_tail()}")
            try:
                status, _, body = request(self.port, "GET", "/health", host=self.host)
                if status == 200:
                    return json.loads(body)
                last = (status, body)
            except OSError as e:
                last = e
            time.sleep(0.02)
        raise AssertionError(f"/health not 200 within {timeout} s (last {last}); stderr: {self.stderr_tail()}")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            rc = self.proc.wait(timeout=timeout)
            _RUNNING.discard(self)
            return rc
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"server still running {timeout} s after signal {sig}; stderr: {self.stderr_tail()}")

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        _RUNNING.discard(self)


def request(
    port: int,
    method: str,
    path: str,
    body: Optional[bytes] = None,
    headers: Optional[Mapping[str, str]] = None,
    host: str = "127.0.0.1",
    timeout: float = 30.0,
) -> Tuple[int, Dict[str, str], bytes]:
    """One HTTP exchange on a fresh connection: (status, lower-cased headers, body)."""
    conn = http.client.HTTPConnection(host, port, timeout=timeout)
    try:
        conn.request(method, path, body=body, headers=dict(headers or {}))
        resp = conn.getresponse()
        data = resp.read()
        return resp.status, {k.lower(): v for k, v in resp.getheaders()}, data
    finally:
        conn.close()


def raw_exchange(port: int, data: bytes, host: str = "127.0.0.1", timeout: float = 15.0) -> bytes:
    """Writes raw bytes and reads until the server closes or stops sending: for malformed or oversized
    requests that http.client would refuse to build."""
    with socket.create_connection((host, port), timeout=timeout) as s:
        try:
            s.sendall(data)
        except (BrokenPipeError, ConnectionResetError):
            pass
        chunks = []
        try:
            while True:
                chunk = s.recv(65536)
                if not chunk:
                    break
                chunks.append(chunk)
                if _complete(b"".join(chunks)):
                    break
        except (socket.timeout, ConnectionResetError):
            pass
    return b"".join(chunks)


def _complete(data: bytes) -> bool:
    head, sep, rest = data.partition(b"\r\n\r\n")
    if not sep:
        return False
    m = re.search(rb"(?im)^content-length:\s*(\d+)", head)
    return m is not None and len(rest) >= int(m.group(1))


def parse_raw_response(data: bytes) -> Tuple[int, Dict[str, str], bytes]:
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {}
    for line in lines[1:]:
        k, _, v = line.partition(":")
        headers[k.strip().lower()] = v.strip()
    return status, headers, body


_SAMPLE = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(.*)\})?\s+(\S+)(\s+\d+)?$")
_LABEL = re.compile(r'([a-zA-Z_][a-zA-Z0-9_]*)="((?:[^"\\]|\\.)*)"')


def parse_metrics(text: str) -> Dict[Tuple[str, frozenset], float]:
    """Prometheus text format -> {(name, frozenset(labels)): value}; raises on a malformed sample line."""
    out: Dict[Tuple[str, frozenset], float] = {}
    for line in text.splitlines():
        if not line or line.startswith("#"):
            continue
        m = _SAMPLE.match(line)
        if not m:
            raise AssertionError(f"malformed metrics line: {line!r}")
        labels = frozenset(_LABEL.findall(m.group(3) or ""))
        out[(m.group(1), labels)] = float(m.group(4))
    return out


def metric(samples: Dict[Tuple[str, frozenset], float], name: str, **labels: str) -> float:
    """Sum of the samples of ``name`` whose labels include ``labels`` (0 when none)."""
    want = set(labels.items())
    return sum(v for (n, ls), v in samples.items() if n == name and want <= set(ls))
