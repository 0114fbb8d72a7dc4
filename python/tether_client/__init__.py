"""Python client of the `tether serve` HTTP API: send an observation, get a robot action chunk back."""

__version__ = "0.1.0"

from .client import ActResult, Episode, ReflexClient, TetherClient  # noqa: E402
from .errors import (  # noqa: E402
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
from .images import encode_image  # noqa: E402

__all__ = [
    "ActResult",
    "AuthenticationError",
    "CircuitOpenError",
    "DeadlineExceededError",
    "Episode",
    "InvalidRequestError",
    "ReflexClient",
    "RequestTimeoutError",
    "ServerBusyError",
    "ServerError",
    "TetherClient",
    "TetherConnectionError",
    "TetherError",
    "TetherTimeoutError",
    "encode_image",
]
