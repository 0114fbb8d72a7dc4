"""HTTP client of `tether serve`: one keep-alive connection, msgpack (or JSON) requests, retries on 503, typed
errors."""

from __future__ import annotations

import contextlib
import email.utils
import http.client
import json
import numbers
import os
import random
import socket
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Union
from urllib.parse import urlsplit

import numpy as np

from . import __version__
from .errors import (
    AuthenticationError,
    CircuitOpenError,
    DeadlineExceededError,
    InvalidRequestError,
    RequestTimeoutError,
    ServerBusyError,
    ServerError,
    TetherConnectionError,
    TetherError,
    TetherTimeoutError,
)
from .images import ImageLike, encode_image, image_bytes

try:  # a declared dependency; without it the client sends JSON
    import msgpack
except ImportError:  # pragma: no cover - exercised only without the package
    msgpack = None  # type: ignore[assignment]

MSGPACK = "application/msgpack"

REQUEST_ID_HEADER = "X-Tether-Request-ID"
# Fields every /act answer has; the others come from the safety wedges the server runs.
_CORE_ACT_FIELDS = frozenset({"actions", "num_actions", "action_dim", "latency_ms", "inference_mode", "model_hash",
                              "request_id", "episode_id", "batch_size", "warnings"})


@dataclass(frozen=True)
class ActResult:
    """The answer of ``POST /act``.

    Attributes:
        actions: float32 array ``[num_actions, action_dim]`` in robot units (after un-normalisation).
        latency_ms: server-side milliseconds per stage: ``total``, ``queue``, ``preprocess``, ``vision``,
            ``prefix``, ``denoise``, ``postprocess``.
        request_id: the id the server used (the one sent, or one it generated).
        episode_id: the episode id sent with the request, or None.
        batch_size: how many requests shared the forward pass.
        warnings: server warnings, e.g. a camera without an image.
        model_hash: ``"sha256:<hex>"`` of the served ``model.safetensors``.
        inference_mode: ``{"backend", "precision", "gemm"}``.
        round_trip_ms: wall time of the HTTP exchange seen by the client (retries included).
        wedges: what the server's safety wedges did, for those enabled (``action_source``, ``guard_clamped``,
            ``guard_violations``, ``deadline_exceeded``, ``denoise_steps_used``, ``action_skipped``,
            ``fallback_used``, ``circuit_state``, ``injected_latency_ms``, ``rtc_applied``, ``joint_names``...).
        raw: the decoded JSON body, as received.
    """

    actions: np.ndarray
    latency_ms: Dict[str, float]
    request_id: str
    episode_id: Optional[str]
    batch_size: int
    warnings: List[str]
    model_hash: str
    inference_mode: Dict[str, str]
    round_trip_ms: float
    wedges: Dict[str, Any] = field(default_factory=dict)
    raw: Dict[str, Any] = field(repr=False, default_factory=dict)

    @property
    def deadline_exceeded(self) -> bool:
        return bool(self.wedges.get("deadline_exceeded", False))

    @property
    def guard_clamped(self) -> bool:
        return bool(self.wedges.get("guard_clamped", False))

    @property
    def action_source(self) -> str:
        """``model``, ``cache`` (similarity skip), ``last_good`` (deadline miss) or ``fallback``."""
        return str(self.wedges.get("action_source", "model"))

    @property
    def num_actions(self) -> int:
        return int(self.actions.shape[0])

    @property
    def action_dim(self) -> int:
        return int(self.actions.shape[1])


@dataclass
class _Response:
    status: int
    headers: Dict[str, str]  # lower-cased names
    body: bytes
    parsed: Any = None  # the body already decoded, when the transport carries structured data (ZMQ's msgpack)

    def header(self, name: str) -> Optional[str]:
        return self.headers.get(name.lower())

    def json(self) -> Any:
        """The body decoded: msgpack when the server said so (``Content-Type: application/msgpack``), else JSON."""
        if self.parsed is not None:
            return self.parsed
        if msgpack is not None and (self.header("Content-Type") or "").split(";")[0].strip().lower() == MSGPACK:
            try:
                return msgpack.unpackb(self.body, raw=False)
            except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError) as e:
                raise ValueError(f"malformed msgpack body: {e}") from e
        return json.loads(self.body.decode("utf-8"))


class _NoDelay:
    """Sets TCP_NODELAY once connected: http.client sends the header and the body in two writes, and Nagle would
    hold the body's last segment until the server acknowledges the header."""

    sock: Any

    def connect(self) -> None:
        super().connect()  # type: ignore[misc]
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class _HTTPConnection(_NoDelay, http.client.HTTPConnection):
    pass


class _HTTPSConnection(_NoDelay, http.client.HTTPSConnection):
    pass


class Episode:
    """Handle returned by :meth:`TetherClient.episode`; its :meth:`act` sends the episode's id."""

    def __init__(self, client: "TetherClient", episode_id: str) -> None:
        self.client = client
        self.episode_id = episode_id

    def act(self, image: Optional[ImageLike] = None, **kwargs: Any) -> ActResult:
        kwargs.setdefault("episode_id", self.episode_id)
        return self.client.act(image, **kwargs)

    def __repr__(self) -> str:
        return f"Episode({self.episode_id!r})"


def _parse_retry_after(value: Optional[str]) -> Optional[float]:
    """Seconds from a Retry-After header (delta-seconds or HTTP date); None when absent or unreadable."""
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when is None:
        return None
    return max(0.0, when.timestamp() - time.time())


class TetherClient:
    """Client of one ``tether serve`` endpoint.

    One HTTP/1.1 keep-alive connection is opened lazily and reused by every call; :meth:`close` (or leaving a
    ``with`` block) closes it. Calls from several threads are safe but serialised on that connection: use one
    client per thread to run requests concurrently (the server batches them).

    Args:
        url: base URL, e.g. ``"http://127.0.0.1:8000"`` (``https://`` works too; a path prefix is kept).
        api_key: sent as ``Authorization: Bearer <key>``. ``None`` reads the ``TETHER_API_KEY`` environment
            variable; ``""`` sends no key.
        timeout: socket timeout in seconds for connecting and for each read.
        retries: how many times a 503 (``not_ready`` while the model warms up, ``queue_full``) is retried on
            ``/act`` and ``/config`` before :class:`ServerBusyError` is raised.
        backoff: first retry delay in seconds; it doubles each retry up to ``max_backoff``. A ``Retry-After``
            header longer than that delay is honoured instead. Each delay gets up to 10% random jitter.
        max_backoff: cap of the exponential delay.
        max_retry_wait: bound on the total time slept in retries of one call; a retry that would exceed it is
            not attempted.
        body_format: how ``/act`` bodies travel over HTTP: ``"msgpack"`` (``Content-Type: application/msgpack``,
            images as raw bytes, the answer in msgpack too) or ``"json"`` (images in base64). ``None``: msgpack when
            the ``msgpack`` package is installed (it is a dependency of ``tether-client``), else JSON. Use
            ``"json"`` with servers older than msgpack bodies.
    """

    def __init__(
        self,
        url: str = "http://127.0.0.1:8000",
        api_key: Optional[str] = None,
        timeout: float = 10.0,
        retries: int = 8,
        backoff: float = 0.1,
        max_backoff: float = 2.0,
        max_retry_wait: float = 30.0,
        transport: str = "http",
        zmq_url: Optional[str] = None,
        zmq_server_key: Optional[str] = None,
        body_format: Optional[str] = None,
    ) -> None:
        if body_format is None:
            body_format = "msgpack" if msgpack is not None else "json"
        if body_format not in ("msgpack", "json"):
            raise ValueError(f"body_format must be 'msgpack' or 'json', got {body_format!r}")
        if body_format == "msgpack" and msgpack is None:
            raise ValueError("body_format='msgpack' needs the msgpack package: pip install msgpack")
        if transport not in ("http", "zmq"):
            raise ValueError(f"transport must be 'http' or 'zmq', got {transport!r}")
        if transport == "zmq" and not zmq_url:
            raise ValueError("transport='zmq' needs zmq_url, e.g. 'tcp://127.0.0.1:5556' (tether serve --zmq-port)")
        parts = urlsplit(url if "://" in url else "http://" + url)
        if parts.scheme not in ("http", "https"):
            raise ValueError(f"unsupported URL scheme {parts.scheme!r} in {url!r} (use http:// or https://)")
        if not parts.hostname:
            raise ValueError(f"no host in URL {url!r}")
        if retries < 0 or backoff < 0 or max_backoff < 0 or max_retry_wait < 0 or timeout <= 0:
            raise ValueError("retries, backoff, max_backoff and max_retry_wait must be >= 0 and timeout > 0")
        self.url = url
        self._scheme = parts.scheme
        self._host = parts.hostname
        self._port = parts.port or (443 if parts.scheme == "https" else 80)
        self._prefix = parts.path.rstrip("/")
        self.api_key = os.environ.get("TETHER_API_KEY") if api_key is None else api_key
        self.timeout = timeout
        self.retries = retries
        self.backoff = backoff
        self.max_backoff = max_backoff
        self.max_retry_wait = max_retry_wait
        self._conn: Optional[http.client.HTTPConnection] = None
        self._conn_uses = 0
        self._lock = threading.Lock()
        self._local = threading.local()  # per-thread current episode id
        self.transport = transport
        self.body_format = body_format
        self._zmq = None  # transport="zmq": act() goes over this channel; everything else stays on HTTP
        if transport == "zmq":
            from .zmq_transport import ZmqChannel

            self._zmq = ZmqChannel(str(zmq_url), timeout, zmq_server_key)

    # -- connection -------------------------------------------------------------------------------------------

    def __enter__(self) -> "TetherClient":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def close(self) -> None:
        """Closes the keep-alive connection; a later call opens a new one."""
        with self._lock:
            self._drop_connection()
        if self._zmq is not None:
            self._zmq.close()

    def _drop_connection(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        self._conn_uses = 0

    def _connection(self) -> http.client.HTTPConnection:
        if self._conn is None:
            cls = _HTTPSConnection if self._scheme == "https" else _HTTPConnection
            self._conn = cls(self._host, self._port, timeout=self.timeout)
            self._conn_uses = 0
        return self._conn

    def _headers(self, extra: Optional[Mapping[str, str]]) -> Dict[str, str]:
        headers = {"User-Agent": f"tether-client/{__version__}", "Accept": "application/json"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        if extra:
            headers.update(extra)
        return headers

    def _exchange_once(self, method: str, path: str, body: Optional[bytes], headers: Dict[str, str]) -> _Response:
        """One request on the current connection; raises OSError/HTTPException when no answer came."""
        conn = self._connection()
        self._conn_uses += 1
        try:
            conn.request(method, self._prefix + path, body=body, headers=headers)
        except (BrokenPipeError, ConnectionResetError):
            # The server may answer early (413, 401) and close before reading the whole body; its answer can
            # still be waiting in the socket; when it is not, reading it fails and the caller handles that.
            resp = conn.getresponse()
            data = resp.read()
            self._drop_connection()
            return _Response(resp.status, {k.lower(): v for k, v in resp.getheaders()}, data)
        resp = conn.getresponse()
        data = resp.read()
        if resp.will_close:
            self._drop_connection()
        return _Response(resp.status, {k.lower(): v for k, v in resp.getheaders()}, data)

    def _exchange(self, method: str, path: str, body: Optional[bytes], headers: Dict[str, str]) -> _Response:
        if self._zmq is not None and path == "/act" and isinstance(body, dict):
            return _Response(*self._zmq.exchange(body))
        with self._lock:
            for attempt in range(2):
                reused = self._conn is not None and self._conn_uses > 0
                try:
                    return self._exchange_once(method, path, body, headers)
                except socket.timeout as e:
                    self._drop_connection()
                    raise TetherTimeoutError(
                        f"{method} {path}: no answer from {self._host}:{self._port} within {self.timeout} s",
                        code="timeout",
                    ) from e
                except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError) as e:
                    self._drop_connection()
                    # Almost always an idle keep-alive connection the server had closed. Every endpoint is free of
                    # side effects (an /act sent twice only costs one more inference), so one resend on a fresh
                    # connection is safe.
                    if reused and attempt == 0:
                        continue
                    raise TetherConnectionError(
                        f"{method} {path}: connection to {self._host}:{self._port} lost: {e}",
                        code="connection_error",
                    ) from e
                except (OSError, http.client.HTTPException) as e:
                    self._drop_connection()
                    raise TetherConnectionError(
                        f"{method} {path}: cannot reach {self._host}:{self._port}: {e}", code="connection_error"
                    ) from e
        raise AssertionError("unreachable")

    # -- retries and errors -----------------------------------------------------------------------------------

    def _retry_delay(self, attempt: int, retry_after: Optional[float]) -> float:
        delay = min(self.max_backoff, self.backoff * (2.0**attempt))
        if retry_after is not None:
            delay = max(delay, retry_after)
        return delay * (1.0 + 0.1 * random.random())

    def _request(
        self,
        method: str,
        path: str,
        body: Optional[bytes] = None,
        headers: Optional[Mapping[str, str]] = None,
        retry: bool = False,
    ) -> _Response:
        all_headers = self._headers(headers)
        waited = 0.0
        attempt = 0
        while True:
            response = self._exchange(method, path, body, all_headers)
            if response.status != 503 or not retry:
                return response
            retry_after = _parse_retry_after(response.header("Retry-After"))
            if attempt >= self.retries:
                self._raise_for_status(response, f"after {attempt} retries")
            delay = self._retry_delay(attempt, retry_after)
            if waited + delay > self.max_retry_wait:
                self._raise_for_status(response, f"after {attempt} retries ({waited:.1f} s waited)")
            time.sleep(delay)
            waited += delay
            attempt += 1

    @staticmethod
    def _raise_for_status(response: _Response, context: str = "") -> None:
        if response.status < 400:
            return
        request_id = response.header(REQUEST_ID_HEADER)
        body: Optional[Dict[str, Any]] = None
        code = f"http_{response.status}"
        message = response.body.decode("utf-8", "replace").strip() or http.client.responses.get(
            response.status, "error"
        )
        try:
            decoded = response.json()
            if isinstance(decoded, dict):
                body = decoded
                err = decoded.get("error")
                if isinstance(err, dict):
                    code = str(err.get("code", code))
                    message = str(err.get("message", message))
        except (ValueError, UnicodeDecodeError):
            pass
        if context:
            message = f"{message} ({context})"
        kwargs: Dict[str, Any] = dict(status=response.status, code=code, request_id=request_id, body=body)
        status = response.status
        if status == 401:
            raise AuthenticationError(message, **kwargs)
        if status == 408:
            raise RequestTimeoutError(message, **kwargs)
        if status == 504 and code == "deadline_exceeded":
            raise DeadlineExceededError(message, **kwargs)
        if status == 503 and code == "circuit_open":
            raise CircuitOpenError(message, retry_after=_parse_retry_after(response.header("Retry-After")), **kwargs)
        if status == 503:
            raise ServerBusyError(message, retry_after=_parse_retry_after(response.header("Retry-After")), **kwargs)
        if 400 <= status < 500:
            raise InvalidRequestError(message, **kwargs)
        raise ServerError(message, **kwargs)

    @staticmethod
    def _json_body(response: _Response) -> Dict[str, Any]:
        try:
            decoded = response.json()
        except (ValueError, UnicodeDecodeError) as e:
            decoded = e
        if not isinstance(decoded, dict):
            raise TetherError(
                f"response is not a JSON object: {response.body[:200]!r}",
                status=response.status,
                code="bad_response",
                request_id=response.header(REQUEST_ID_HEADER),
            )
        return decoded

    # -- endpoints --------------------------------------------------------------------------------------------

    def act(
        self,
        image: Optional[ImageLike] = None,
        *,
        images: Optional[Mapping[str, ImageLike]] = None,
        state: Union[Sequence[float], np.ndarray],
        instruction: str,
        seed: Optional[int] = None,
        episode_id: Optional[str] = None,
        request_id: Optional[str] = None,
        prev_actions: Optional[Union[Sequence[Sequence[float]], np.ndarray]] = None,
        inference_delay: Optional[int] = None,
    ) -> ActResult:
        """Runs the policy on one observation and returns its action chunk.

        Args:
            image: the image of the model's first camera (see :func:`tether_client.images.encode_image` for
                the accepted forms: numpy array, PNG/JPEG bytes, file path).
            images: ``{camera: image}``; the camera is the checkpoint's key (``"observation.images.front"``) or
                its short form (``"front"``). Exclusive with ``image``. A camera left out is handled as lerobot
                does and reported in ``warnings``.
            state: the robot state, ``state_dim`` finite numbers in robot units.
            instruction: the task in natural language.
            seed: noise seed (int >= 0); the same seed and inputs give the same actions.
            episode_id: sent as is; defaults to the id of the enclosing :meth:`episode` block, if any.
            request_id: sent as ``X-Tether-Request-ID`` (1..128 chars of ``[A-Za-z0-9._:-]``).
            prev_actions: real-time chunking (server started with ``--rtc``): the previous chunk's actions not yet
                executed, ``[n, action_dim]`` in robot units; the new chunk is guided to continue them.
            inference_delay: real-time chunking: how many of ``prev_actions`` will still run while this request is
                computed (they are followed exactly, the rest with decaying weight).

        Raises:
            ValueError / TypeError: invalid arguments, detected before anything is sent.
            TetherError subclasses: see the module documentation.
        """
        if image is not None and images is not None:
            raise ValueError("pass either image= or images=, not both")
        if not isinstance(instruction, str):
            raise TypeError(f"instruction must be a str, got {type(instruction).__name__}")
        state_array = np.asarray(state, dtype=np.float64)
        if state_array.ndim != 1:
            raise ValueError(f"state must be a 1-D sequence of numbers, got shape {state_array.shape}")
        if not np.all(np.isfinite(state_array)):
            raise ValueError("state contains NaN or Inf")
        payload: Dict[str, Any] = {"instruction": instruction, "state": [float(v) for v in state_array]}
        binary = self._zmq is not None or self.body_format == "msgpack"
        encode: Any = image_bytes if binary else encode_image  # msgpack carries bytes: no base64
        if image is not None:
            payload["image"] = encode(image)
        if images is not None:
            payload["images"] = {str(cam): encode(img) for cam, img in images.items()}
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
                raise ValueError(f"seed must be an int >= 0, got {seed!r}")
            payload["seed"] = int(seed)
        if episode_id is None:
            episode_id = getattr(self._local, "episode_id", None)
        if episode_id is not None:
            payload["episode_id"] = str(episode_id)
        if prev_actions is not None:
            prev = np.asarray(prev_actions, dtype=np.float64)
            if prev.ndim != 2 or prev.shape[0] == 0 or not np.all(np.isfinite(prev)):
                raise ValueError(f"prev_actions must be a finite [n, action_dim] array, got shape {prev.shape}")
            rtc: Dict[str, Any] = {"prev_actions": prev.tolist()}
            if inference_delay is not None:
                if isinstance(inference_delay, bool) or not isinstance(inference_delay, numbers.Integral) or inference_delay < 0:
                    raise ValueError(f"inference_delay must be an int >= 0, got {inference_delay!r}")
                rtc["inference_delay"] = int(inference_delay)
            payload["rtc"] = rtc
        elif inference_delay is not None:
            raise ValueError("inference_delay needs prev_actions")
        if self._zmq is None and self.body_format == "msgpack":
            headers = {"Content-Type": MSGPACK, "Accept": MSGPACK}
        else:
            headers = {"Content-Type": "application/json"}
        if request_id is not None:
            headers[REQUEST_ID_HEADER] = request_id
        body: Any
        if self._zmq is not None:  # msgpack over ZMQ: the key and the request id travel as fields
            if self.api_key:
                payload["api_key"] = self.api_key
            if request_id is not None:
                payload["request_id"] = request_id
            body = payload
        elif self.body_format == "msgpack":
            body = msgpack.packb(payload, use_bin_type=True)
        else:
            body = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode("utf-8")

        start = time.perf_counter()
        response = self._request("POST", "/act", body, headers, retry=True)
        round_trip_ms = (time.perf_counter() - start) * 1000.0
        self._raise_for_status(response)
        return self._parse_act(response, round_trip_ms)

    def _parse_act(self, response: _Response, round_trip_ms: float) -> ActResult:
        data = self._json_body(response)
        try:
            actions = np.asarray(data["actions"], dtype=np.float32)
            num_actions, action_dim = int(data["num_actions"]), int(data["action_dim"])
            if actions.shape != (num_actions, action_dim):
                raise ValueError(f"actions have shape {actions.shape}, expected ({num_actions}, {action_dim})")
            return ActResult(
                actions=actions,
                latency_ms={str(k): float(v) for k, v in data.get("latency_ms", {}).items()},
                request_id=str(data.get("request_id") or response.header(REQUEST_ID_HEADER) or ""),
                episode_id=data.get("episode_id"),
                batch_size=int(data.get("batch_size", 1)),
                warnings=[str(w) for w in data.get("warnings", [])],
                model_hash=str(data.get("model_hash", "")),
                inference_mode=dict(data.get("inference_mode", {})),
                round_trip_ms=round_trip_ms,
                wedges={k: v for k, v in data.items() if k not in _CORE_ACT_FIELDS},
                raw=data,
            )
        except (KeyError, TypeError, ValueError) as e:
            raise TetherError(
                f"malformed /act response: {e}",
                status=response.status,
                code="bad_response",
                request_id=response.header(REQUEST_ID_HEADER),
            ) from e

    def health(self) -> Dict[str, Any]:
        """``GET /health``: ``{"status": "ok"|"unavailable", "state": ..., "model_hash": ...}``.

        Returned for 200 and for 503 (loading, warming): it reports state rather than failing. Never retried."""
        response = self._request("GET", "/health")
        if response.status not in (200, 503):
            self._raise_for_status(response)
        return self._json_body(response)

    def ready(self) -> bool:
        """``GET /ready``: True once the model is loaded and warmed up."""
        response = self._request("GET", "/ready")
        if response.status not in (200, 503):
            self._raise_for_status(response)
        return response.status == 200 and bool(self._json_body(response).get("ready"))

    def live(self) -> bool:
        """``GET /live``: True while the process answers."""
        response = self._request("GET", "/live")
        self._raise_for_status(response)
        return bool(self._json_body(response).get("live"))

    def wait_until_ready(self, timeout: float = 60.0, interval: float = 0.1) -> Dict[str, Any]:
        """Polls ``/health`` until it answers 200 and returns its body. Connection errors count as not ready
        (the server may still be starting). Raises :class:`ServerBusyError` after ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        last: Any = None
        while True:
            try:
                response = self._request("GET", "/health")
                if response.status == 200:
                    return self._json_body(response)
                last = f"{response.status} {response.body[:200]!r}"
            except TetherConnectionError as e:
                last = e
            if time.monotonic() >= deadline:
                raise ServerBusyError(f"server not ready after {timeout} s (last: {last})", code="not_ready")
            time.sleep(interval)

    def config(self) -> Dict[str, Any]:
        """``GET /config``: the served model's cameras, state/action sizes, normalisation and the limits."""
        response = self._request("GET", "/config", retry=True)
        self._raise_for_status(response)
        return self._json_body(response)

    def metrics(self) -> str:
        """``GET /metrics``: the Prometheus text exposition."""
        response = self._request("GET", "/metrics", headers={"Accept": "text/plain"})
        self._raise_for_status(response)
        return response.body.decode("utf-8")

    @contextlib.contextmanager
    def episode(self, episode_id: Optional[str] = None) -> Iterator[Episode]:
        """Context manager for one robot episode: every :meth:`act` in the block (on this thread) sends the same
        ``episode_id``, a fresh uuid4 unless one is given. Nested blocks restore the outer id on exit."""
        new_id = episode_id if episode_id is not None else str(uuid.uuid4())
        previous = getattr(self._local, "episode_id", None)
        self._local.episode_id = new_id
        try:
            yield Episode(self, new_id)
        finally:
            self._local.episode_id = previous

    @property
    def episode_id(self) -> Optional[str]:
        """The id of the enclosing :meth:`episode` block on this thread, or None."""
        return getattr(self._local, "episode_id", None)

    def __repr__(self) -> str:
        return f"TetherClient({self.url!r})"


ReflexClient = TetherClient
"""Alias of :class:`TetherClient`."""
