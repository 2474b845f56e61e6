"""Reading a weights file (safetensors, or a torch state dict) without unpickling anything."""

from __future__ import annotations

import io
import json
import pickle
import re
import struct
import sys
import zipfile
import zlib
from pathlib import Path

import torch

from prop_cli.constants import KEY_BITS_MAX, KEY_BITS_MIN
from prop_cli.errors import PropError

SAFETENSORS_EXTS = (".safetensors",)
TORCH_EXTS = (".pt", ".pth", ".bin")
WEIGHT_EXTS = SAFETENSORS_EXTS + TORCH_EXTS
# Wrappers that training scripts commonly put around the state dict.
STATE_DICT_ENTRIES = ("state_dict", "model_state_dict")
_ZIP_MAGIC = b"PK\x03\x04"  # torch.save's format since 1.6 is a zip archive
# torch.save's legacy format starts by pickling its magic number 0x1950a86a20f9469cfc6c (as LONG1).
_LEGACY_MAGIC = b"\x8a\nl\xfc\x9cF\xf9 j\xa8P\x19"
_NPY_MAGIC = b"\x93NUMPY"  # numpy's .npy header (an .npz is a zip of them)
_MAX_HEADER = 100 << 20  # safetensors caps its JSON header at 100 MB
_DOS_DIRECTORY = 0x10  # the MS-DOS "directory" bit of a zip entry's external attributes
# What zipfile raises on a damaged archive: bad CRC or headers (BadZipFile), a broken deflate stream
# (zlib.error), a cut-off member (EOFError), an unknown compression method or encryption, bad names.
ZIP_ERRORS = (
    zipfile.BadZipFile, zlib.error, OSError, EOFError, NotImplementedError, RuntimeError, ValueError,
    IndexError, KeyError, struct.error,
)  # fmt: skip


def sniff(path: Path) -> str | None:
    """'safetensors', 'torch' or None, from the first bytes of the file."""
    try:
        with open(path, "rb") as f:
            head = f.read(32)
    except OSError:
        return None
    if len(head) >= 9:
        (n,) = struct.unpack("<Q", head[:8])
        if 2 <= n <= _MAX_HEADER and head[8:9] == b"{":
            return "safetensors"
    if head.startswith(_ZIP_MAGIC) or (head.startswith(b"\x80") and _LEGACY_MAGIC in head):
        return "torch"
    return None


def is_weights_file(path: Path) -> bool:
    """A file with a weights suffix, or one whose first bytes say safetensors or torch."""
    return path.is_file() and (path.suffix.lower() in WEIGHT_EXTS or sniff(path) is not None)


WEIGHTS_ARE = (
    "the checkpoint is the model you start from (.safetensors, .pt, .pth, .bin or a folder: `prop formats`)"
)


def other_kind(path: Path) -> tuple[str, str] | None:
    """(what it is, where it goes) for a file prop reads in another role, given as a checkpoint: a data
    file (.npz, which is a zip archive as torch files are), an array (.npy), an ONNX graph, a key file.
    None for anything else (it is then read as weights and any error is about that)."""
    head = _head(path)
    suffix = path.suffix.lower()
    if suffix == ".npz" or (head.startswith(_ZIP_MAGIC) and _npy_members(path)):
        return "a data file (.npz)", f"{WEIGHTS_ARE}; the data goes in --data"
    if head.startswith(_NPY_MAGIC):
        return "an array file (.npy)", f"{WEIGHTS_ARE}; arrays go in prop run --input"
    if suffix == ".onnx":
        return "an ONNX graph (.onnx)", f"{WEIGHTS_ARE}: the torch checkpoint the graph was exported from"
    size = path.stat().st_size
    if sniff(path) is None and suffix in ("", ".bin", ".key") and KEY_BITS_MIN <= 8 * size <= KEY_BITS_MAX:
        return f"a key file ({size} bytes, as prop keygen writes)", f"{WEIGHTS_ARE}; keys go in --key-file"
    return None


def _head(path: Path, n: int = 8) -> bytes:
    try:
        with open(path, "rb") as f:
            return f.read(n)
    except OSError:
        return b""


def _npy_members(path: Path) -> bool:
    """Whether the zip archive at ``path`` holds numpy arrays only (np.savez's layout)."""
    try:
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
    except ZIP_ERRORS:
        return False
    return bool(names) and all(n.endswith(".npy") for n in names)


def _check_file(path: Path) -> None:
    if not path.exists():
        raise PropError(f"checkpoint {path} does not exist", "check the path")
    if path.is_dir():
        raise PropError(
            f"checkpoint {path} is a directory",
            "pass the weights file itself (.safetensors, .pt, .pth or .bin)",
        )
    if path.stat().st_size == 0:
        raise PropError(f"checkpoint {path} is empty", "re-export the checkpoint")


def _read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            metadata = dict(f.metadata() or {})
            tensors = {name: f.get_tensor(name) for name in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError, KeyError, json.JSONDecodeError) as e:
        raise PropError(
            f"checkpoint {path} is not a readable safetensors file ({e})",
            "re-export it with safetensors.torch.save_file",
        ) from None
    return tensors, metadata


def safetensors_shapes(path: Path) -> dict[str, tuple[int, ...]]:
    """Each tensor's name and shape from a safetensors file's header; no tensor is read."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            return {name: tuple(f.get_slice(name).get_shape()) for name in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError, KeyError, json.JSONDecodeError) as e:
        raise PropError(
            f"checkpoint {path} is not a readable safetensors file ({e})",
            "re-export it with safetensors.torch.save_file",
        ) from None


# safetensors' dtype names (its header) as torch's.
_ST_DTYPES = {
    "F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
    "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8,
    "BOOL": torch.bool,
}  # fmt: skip


def safetensors_dtypes(path: Path) -> dict[str, torch.dtype]:
    """Each tensor's name and dtype from a safetensors file's header (no tensor read): the dtype the
    checkpoint holds it in, which a bundle's base keeps (a bf16 checkpoint gives a bf16 base). A dtype
    torch has no name for here is left out (the tensor is then written as the module holds it)."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            named = {name: f.get_slice(name).get_dtype() for name in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError, KeyError, json.JSONDecodeError) as e:
        raise PropError(
            f"checkpoint {path} is not a readable safetensors file ({e})",
            "re-export it with safetensors.torch.save_file",
        ) from None
    return {n: _ST_DTYPES[d] for n, d in named.items() if d in _ST_DTYPES}


def load_into(module: torch.nn.Module, path: Path, as_held: bool = False) -> None:
    """``module.load_state_dict`` (strict) from a safetensors file, one tensor at a time: memory stays
    the module's plus one tensor, not the module's plus the whole file's (a 450 M-parameter policy: 1.8
    GB less at its peak). Names and shapes must match exactly, as for ``load_state_dict(strict=True)``.
    ``as_held``: each tensor takes the file's values in the file's dtype instead of a copy in the
    module's (a bf16 file into a module built fp32 never holds an fp32 copy: the module's own storage,
    allocated but never written, is freed), read straight into memory of its own (``_Held``)."""
    from safetensors import SafetensorError, safe_open

    targets = module.state_dict(keep_vars=True)
    try:
        with safe_open(str(path), framework="pt", device="cpu") as f, open(path, "rb") as raw:
            held = _Held(raw) if as_held else None
            names = set(f.keys())
            if names != set(targets):
                name = sorted(names ^ set(targets))[0]
                raise PropError(
                    f"checkpoint {path}: tensor {name[:120]!r} is "
                    f"{'not in the model' if name in names else 'missing'}",
                    "check that the checkpoint and its config belong together",
                )
            with torch.no_grad():
                for name in sorted(names):
                    shape = tuple(f.get_slice(name).get_shape())
                    if shape != tuple(targets[name].shape):
                        raise PropError(
                            f"checkpoint {path}: tensor {name[:120]!r} has shape {shape}, the model's "
                            f"{tuple(targets[name].shape)}",
                            "check that the checkpoint and its config belong together",
                        )
                    if held is not None:
                        targets[name].data = held.read(name, f)
                    else:
                        targets[name].copy_(f.get_tensor(name))
    except (SafetensorError, OSError, ValueError, KeyError, json.JSONDecodeError) as e:
        raise PropError(
            f"checkpoint {path} is not a readable safetensors file ({e})",
            "re-export it with safetensors.torch.save_file",
        ) from None


class _Held:
    """A safetensors file's tensors read one at a time into memory of their own, in the file's dtype
    (``load_into``'s ``as_held``). safetensors' own ``get_tensor`` maps the file: the pages read stay
    in the process's resident memory while the file is open, beside a copy (a real-size SmolVLA's bf16
    load: 2.55 GiB at its peak against 1.71 GiB so, docs/speed.md), and a tensor not copied would
    change if the file did."""

    def __init__(self, raw) -> None:
        size = int.from_bytes(raw.read(8), "little")
        self.raw, self.base = raw, 8 + size
        self.header = json.loads(raw.read(size))  # safe_open has checked it (offsets inside the file)

    def read(self, name: str, f) -> torch.Tensor:
        """Tensor ``name``; one of a dtype this reader does not know, a copy of ``f.get_tensor``'s."""
        entry = self.header[name]
        # This header was read from a second open of the path: it must say what safe_open checked (a file
        # swapped in between would otherwise size the allocation below).
        checked = f.get_slice(name)
        if (
            list(entry.get("shape", ())) != list(checked.get_shape())
            or entry.get("dtype") != checked.get_dtype()
        ):
            raise ValueError(f"tensor {name!r} changed while the file was read")
        if entry["dtype"] not in _ST_DTYPES or entry["dtype"] == "BOOL" or sys.byteorder != "little":
            return f.get_tensor(name).clone()
        start, end = entry["data_offsets"]
        t = torch.empty(entry["shape"], dtype=_ST_DTYPES[entry["dtype"]])
        view = memoryview(t.reshape(-1).view(torch.uint8).numpy())
        if len(view) != end - start:
            raise ValueError(f"tensor {name!r}: {end - start} bytes in the file for {len(view)}")
        self.raw.seek(self.base + start)
        done = 0
        while done < len(view):
            n = self.raw.readinto(view[done:])
            if not n:
                raise ValueError(f"tensor {name!r} ends after the file")
            done += n
        return t


def _corrupt(path: Path, e: Exception) -> PropError:
    return PropError(
        f"checkpoint {path} is corrupt or not a torch file ({type(e).__name__})",
        "re-export it with torch.save(model.state_dict(), path) or as .safetensors",
    )


def verify_zip(z: zipfile.ZipFile) -> None:
    """Read every member of an open archive, so zipfile checks each CRC-32 and that each local header
    names the member its central-directory entry does; refuse members marked as folders (torch's
    reader skips those, so a flipped attribute bit would silently drop a tensor). Members stored with
    CRC 0 are opened but not read (torch.save with its CRC option off writes 0)."""
    for info in z.infolist():
        if not info.filename or info.filename.endswith("/") or info.external_attr & _DOS_DIRECTORY:
            raise zipfile.BadZipFile(f"member {info.filename!r} has no name or is marked as a folder")
        with z.open(info) as member:
            while info.CRC and member.read(1 << 20):
                pass


def _check_stored(z: zipfile.ZipFile, name: str) -> None:
    """A torch file's members are stored as they are (torch.save never compresses them): a compressed
    one would inflate in memory, a few kilobytes on disk becoming gigabytes when torch.load reads it."""
    for info in z.infolist():
        if info.compress_type != zipfile.ZIP_STORED:
            raise PropError(
                f"checkpoint {name}: member {info.filename[:80]!r} is compressed, which torch.save never "
                f"does ({info.compress_size} bytes that would inflate to {info.file_size})",
                "re-save it with torch.save(model.state_dict(), path), or as .safetensors",
            )


def check_zip_crc(data: Path | str | io.BytesIO, name: str) -> None:
    """``verify_zip`` for a zip-format torch file, which torch.load does not check: without this a
    flipped bit in a tensor loads as a different weight. Legacy (pickle) torch files have no checksum."""
    if not isinstance(data, io.BytesIO):
        with open(data, "rb") as f:
            if f.read(4) != _ZIP_MAGIC:
                return
    elif data.getbuffer()[:4].tobytes() != _ZIP_MAGIC:
        return
    try:
        with zipfile.ZipFile(data) as z:
            _check_stored(z, name)
            verify_zip(z)
    except ZIP_ERRORS as e:
        raise _corrupt(Path(name), e) from None
    finally:
        if isinstance(data, io.BytesIO):
            data.seek(0)


def load_state_dict(data: Path | str | io.BytesIO, name: str) -> object:
    """``torch.load(weights_only=True)``; a refused object names the class it would have unpickled."""
    check_zip_crc(data, name)
    try:
        return torch.load(data, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as e:
        text = str(e)
        if "Weights only load failed" not in text:
            raise _corrupt(Path(name), e) from None
        # weights_only refused an arbitrary object: that is the point, never retry without it.
        m = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        what = f"it pickles {m.group(1)}" if m else "it pickles objects other than tensors"
        raise PropError(
            f"checkpoint {name} was refused: {what}, and prop never unpickles code",
            "save only the state dict: torch.save(model.state_dict(), path), or use .safetensors",
        ) from None
    except Exception as e:  # torch raises many types (KeyError, RuntimeError, EOFError) on junk
        raise _corrupt(Path(name), e) from None


def _read_torch(path: Path) -> dict[str, torch.Tensor]:
    obj = load_state_dict(str(path), str(path))
    if isinstance(obj, dict):
        for entry in STATE_DICT_ENTRIES:
            if isinstance(obj.get(entry), dict):
                obj = obj[entry]
                break
    if not isinstance(obj, dict):
        raise PropError(
            f"checkpoint {path} holds a {type(obj).__name__}, not a state dict",
            "save a flat dict name -> tensor: torch.save(model.state_dict(), path)",
        )
    bad = [str(k) for k, v in obj.items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        shown = ", ".join(bad[:3]) + (f" (+{len(bad) - 3} more)" if len(bad) > 3 else "")
        raise PropError(
            f"checkpoint {path} is not a flat state dict: entries {shown} are not tensors",
            "save only model.state_dict(), or put it under a 'state_dict' entry",
        )
    return dict(obj)


def read_weights(
    path: str | Path, *, safetensors_only: bool = False
) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors by name plus safetensors metadata ({} for torch files). Never unpickles.
    ``safetensors_only``: a bundle's own weights, which prop always writes as safetensors (read as they
    lie on disk, so memory stays within the file's size); anything else there is refused."""
    path = Path(path)
    _check_file(path)
    known = None if safetensors_only else other_kind(path)
    if known is not None:
        raise PropError(f"checkpoint {path} is {known[0]}, not a model's weights", known[1])
    kind = sniff(path)
    if safetensors_only and kind != "safetensors":
        raise PropError(
            f"{path} is not a safetensors file (prop writes a bundle's weights as safetensors only)",
            "restore the bundle from a trusted copy",
        )
    suffix = path.suffix.lower()
    if suffix not in WEIGHT_EXTS and kind is None:
        raise PropError(
            f"checkpoint {path} has unsupported extension '{path.suffix}'",
            "use .safetensors, .pt, .pth or .bin (`prop formats` lists every format prop reads)",
        )
    if kind is None:
        raise PropError(
            f"checkpoint {path} is not a torch or safetensors file (its first bytes are neither a "
            "safetensors header, a zip archive nor a pickle)",
            "check that it is the checkpoint itself, not a copy that was cut short or another kind of file",
        )
    tensors, metadata = _read_safetensors(path) if kind == "safetensors" else (_read_torch(path), {})
    if not tensors:
        raise PropError(f"checkpoint {path} contains no tensors", "check that it is the right file")
    return tensors, metadata
