"""Turns the image forms a caller has (numpy arrays, encoded files, paths) into the API's IMAGE JSON value."""

from __future__ import annotations

import base64
import os
from typing import Any, Dict, Union

import numpy as np

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"

ImageLike = Union[np.ndarray, bytes, bytearray, memoryview, str, "os.PathLike[str]", Any]
"""An image as :func:`encode_image` accepts it (see there)."""


def _is_encoded(data: bytes) -> bool:
    return data.startswith(PNG_MAGIC) or data.startswith(JPEG_MAGIC)


def _array_to_uint8(array: np.ndarray) -> np.ndarray:
    """Checks the layout and converts the dtype to uint8 HxWx3 without guessing silently."""
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3:
        raise ValueError(f"image array must be HxWx3 (or HxW grayscale), got shape {array.shape}")
    if array.shape[2] == 1:
        array = np.repeat(array, 3, axis=2)
    if array.shape[2] != 3:
        hint = " (channels-first? pass array.transpose(1, 2, 0))" if array.shape[0] in (1, 3) else ""
        raise ValueError(f"image array must have 3 channels in the last axis, got shape {array.shape}{hint}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"image array is empty: shape {array.shape}")

    if array.dtype == np.uint8:
        return array
    if array.dtype == np.bool_:
        raise ValueError("image array of dtype bool is not an image; pass uint8 0..255 or float 0..1")
    if np.issubdtype(array.dtype, np.floating):
        if not np.all(np.isfinite(array)):
            raise ValueError("float image contains NaN or Inf")
        lo, hi = float(array.min()), float(array.max())
        # Floats are read as 0..1 intensities; a 0..255 float array is a common mistake, so it is refused
        # rather than clipped to white.
        if lo < 0.0 or hi > 1.0:
            raise ValueError(
                f"float image values must lie in [0, 1], got [{lo:g}, {hi:g}]; "
                "for 0..255 values pass array.astype(np.uint8)"
            )
        return np.rint(array.astype(np.float64) * 255.0).astype(np.uint8)
    if np.issubdtype(array.dtype, np.integer):
        lo, hi = int(array.min()), int(array.max())
        if lo < 0 or hi > 255:
            raise ValueError(f"integer image values must lie in [0, 255], got [{lo}, {hi}]")
        return array.astype(np.uint8)
    raise ValueError(f"unsupported image dtype {array.dtype}")


def encode_image(image: ImageLike) -> Union[str, Dict[str, Any]]:
    """Returns the JSON value the server expects for one camera image.

    Accepted forms:

    * ``numpy.ndarray`` HxWx3 RGB (HxW or HxWx1 grayscale is replicated to 3 channels). ``uint8`` is sent as is;
      other integer dtypes must hold 0..255; float dtypes must hold 0..1 and are scaled by 255 and rounded
      (a float array outside [0, 1] raises ``ValueError`` instead of being clipped). Sent raw, without
      re-encoding, as ``{"data": base64, "shape": [H, W, 3]}``.
    * ``bytes`` / ``bytearray`` / ``memoryview`` holding a PNG or JPEG file: sent as a base64 string.
    * ``str`` or ``os.PathLike``: the path of a PNG or JPEG file, read and sent as a base64 string.
    * Any object exposing ``__array_interface__`` (a PIL image, for instance): converted with ``numpy.asarray``.

    Raises:
        ValueError: wrong shape, dtype or value range; bytes that are neither PNG nor JPEG.
        TypeError: an object of none of the forms above.
        OSError: a path that cannot be read.
    """
    raw = image_bytes(image)
    if isinstance(raw, bytes):
        return base64.b64encode(raw).decode("ascii")
    return {"data": base64.b64encode(raw["data"]).decode("ascii"), "shape": raw["shape"]}


def image_bytes(image: ImageLike) -> Union[bytes, Dict[str, Any]]:
    """:func:`encode_image` before base64: PNG/JPEG file bytes, or ``{"data": pixel bytes, "shape": [H, W, 3]}``.
    Binary transports (ZMQ) send this as it is."""
    if isinstance(image, (str, os.PathLike)):
        with open(image, "rb") as f:
            data = f.read()
        if not _is_encoded(data):
            raise ValueError(f"{os.fspath(image)!r} is neither a PNG nor a JPEG file")
        return data
    if isinstance(image, (bytes, bytearray, memoryview)):
        data = bytes(image)
        if not _is_encoded(data):
            raise ValueError("image bytes are neither a PNG nor a JPEG file (pass a numpy array for raw pixels)")
        return data
    if not isinstance(image, np.ndarray) and hasattr(image, "__array_interface__"):
        image = np.asarray(image)
    if isinstance(image, np.ndarray):
        pixels = np.ascontiguousarray(_array_to_uint8(image))
        return {
            "data": pixels.tobytes(),
            "shape": [int(pixels.shape[0]), int(pixels.shape[1]), 3],
        }
    raise TypeError(
        f"unsupported image type {type(image).__name__}: pass a numpy array, PNG/JPEG bytes or a file path"
    )
