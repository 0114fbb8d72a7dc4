"""Exceptions raised by the client; one class per kind of failure a caller handles differently."""

from __future__ import annotations

from typing import Any, Dict, Optional


class TetherError(Exception):
    """Base of every error the client raises for a failed request.

    Attributes:
        status: HTTP status of the response (None when no response was received).
        code: the server's stable error code (``"invalid_state"``, ``"queue_full"``...), or a client-side code
            (``"connection_error"``, ``"timeout"``, ``"http_<status>"`` for a non-JSON error body).
        message: the human-readable sentence.
        request_id: the ``X-Tether-Request-ID`` of the response, when there was one.
        body: the decoded JSON body of the error response, when it was JSON.
    """

    def __init__(
        self,
        message: str,
        *,
        status: Optional[int] = None,
        code: Optional[str] = None,
        request_id: Optional[str] = None,
        body: Optional[Dict[str, Any]] = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.request_id = request_id
        self.body = body

    def __str__(self) -> str:
        parts = []
        if self.status is not None:
            parts.append(str(self.status))
        if self.code:
            parts.append(self.code)
        prefix = " ".join(parts)
        suffix = f" (request {self.request_id})" if self.request_id else ""
        return f"{prefix}: {self.message}{suffix}" if prefix else f"{self.message}{suffix}"


class AuthenticationError(TetherError):
    """401: the API key is missing or wrong. The server ran nothing."""


class InvalidRequestError(TetherError):
    """A 4xx other than 401 and 408: the request itself is at fault (bad JSON, wrong state length, unknown camera,
    body or header too large, unknown path, wrong method). Retrying the same request fails the same way."""


class RequestTimeoutError(TetherError):
    """408: the server gave up on the request (reading it, or its per-request deadline)."""


class ServerBusyError(TetherError):
    """503 still returned after the client's retries were used up (``queue_full`` or ``not_ready``).

    ``retry_after`` holds the server's last ``Retry-After`` value in seconds, when it sent one."""

    def __init__(self, message: str, *, retry_after: Optional[float] = None, **kwargs: Any) -> None:
        super().__init__(message, **kwargs)
        self.retry_after = retry_after


class CircuitOpenError(ServerBusyError):
    """503 ``circuit_open``: local inference failed ``--max-consecutive-crashes`` times in a row and the server
    refuses /act until a probe succeeds; ``retry_after`` says when the next probe is let through."""


class DeadlineExceededError(RequestTimeoutError):
    """504 ``deadline_exceeded``: inference missed ``--deadline-ms`` and the episode had no earlier chunk (and no
    fallback) to answer with. Hold the robot and retry."""


class ServerError(TetherError):
    """5xx other than 503, e.g. 500 ``inference_failed``. The server keeps serving other requests."""


class TetherConnectionError(TetherError):
    """No HTTP response: connection refused or reset, DNS failure, or the socket timed out."""


class TetherTimeoutError(TetherConnectionError):
    """The socket timed out waiting for the server (the client's ``timeout``)."""
