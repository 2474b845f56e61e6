"""openpi's msgpack-numpy wire format (openpi_client/msgpack_numpy.py), written here so the server needs no
openpi package: an array is ``{b"__ndarray__": True, b"data", b"dtype", b"shape"}``, a numpy scalar
``{b"__npgeneric__": True, b"data", b"dtype"}``. No pickle anywhere: dtypes that numpy can only rebuild
through Python objects (object, void/structured) are refused both ways, and a message's arrays are
checked against their declared size before numpy sees the bytes."""

from __future__ import annotations

import msgpack
import numpy as np

# Numeric and boolean kinds only: b/i/u/f/c plus fixed-width strings are plain bytes in numpy.
_KINDS = set("biufcSU")


class WireError(ValueError):
    """A message that is not msgpack-numpy as this server takes it; its text is safe to send back."""


def _dtype(value) -> np.dtype:
    try:
        dtype = np.dtype(value.decode() if isinstance(value, bytes) else str(value))
    except (TypeError, ValueError, UnicodeDecodeError):
        raise WireError(f"array dtype {str(value)[:40]!r} is not a numpy dtype") from None
    if dtype.kind not in _KINDS or dtype.hasobject:
        raise WireError(f"array dtype {dtype} is refused (numeric, bool and fixed strings only)")
    return dtype


def _pack(obj):
    if isinstance(obj, (np.ndarray, np.generic)) and (obj.dtype.kind not in _KINDS or obj.dtype.hasobject):
        raise WireError(f"cannot send dtype {obj.dtype}")
    if isinstance(obj, np.ndarray):
        obj = np.ascontiguousarray(obj)
        return {b"__ndarray__": True, b"data": obj.tobytes(), b"dtype": obj.dtype.str, b"shape": obj.shape}
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot serialize {type(obj).__name__}")


def _unpack(obj: dict):
    if b"__ndarray__" in obj:
        dtype = _dtype(obj.get(b"dtype"))
        shape, data = obj.get(b"shape"), obj.get(b"data")
        if (
            not isinstance(data, bytes)
            or not isinstance(shape, (list, tuple))
            or not all(isinstance(n, int) and n >= 0 for n in shape)
        ):
            raise WireError("an array needs bytes 'data' and a 'shape' of non-negative integers")
        if int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != len(data):
            raise WireError(
                f"array data is {len(data)} bytes, not what shape {tuple(shape)} of {dtype} holds"
            )
        return np.frombuffer(data, dtype=dtype).reshape(shape).copy()  # writable: torch takes it as is
    if b"__npgeneric__" in obj:
        dtype = _dtype(obj.get(b"dtype"))
        try:
            return dtype.type(obj.get(b"data"))
        except (TypeError, ValueError, OverflowError):
            raise WireError(f"scalar of dtype {dtype} does not hold its data") from None
    return obj


def packb(obj) -> bytes:
    """``obj`` (dicts, lists, numbers, strings, numpy arrays and scalars) as msgpack-numpy bytes."""
    return msgpack.packb(obj, default=_pack)


def unpackb(data: bytes):
    """msgpack-numpy bytes -> Python objects and numpy arrays."""
    try:
        # msgpack's own caps bound a hostile message's containers; ext types (nothing here) are refused.
        return msgpack.unpackb(data, object_hook=_unpack, strict_map_key=False, max_ext_len=0)
    except WireError:
        raise
    except (ValueError, TypeError, msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as e:
        raise WireError(f"not a msgpack message ({type(e).__name__})") from None
