"""Reading a bundle: the manifest (format version, schema, digest), every file's sha256, the module and
its mode (``modes``). Nothing is loaded before its bytes are checked against the manifest."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import prop_adapters as adapters
from prop_adapters import LoadedModel
from prop_cli import constants as C
from prop_cli.core.keyed_model import KeyedModel
from prop_cli.errors import PropError
from prop_cli.files import RESTORE, TAMPERED, link_error, read, sha256_inside, shown

from . import manifest as schema
from .modes import Mode, load_mode
from .records import SealedState


def read_manifest(path: Path) -> dict:
    path = Path(path)
    if not path.exists():
        raise PropError(
            f"bundle {path} does not exist", "check the path (a directory made by prop personalize)"
        )
    mpath = path / C.MANIFEST
    if mpath.is_symlink():
        raise link_error(path, mpath)
    if path.name == C.MANIFEST and path.is_file():
        raise PropError(
            f"{path} is a bundle's {C.MANIFEST}, not the bundle", f"give the bundle folder {path.parent}"
        )
    if not path.is_dir() or not mpath.is_file():
        raise PropError(
            f"{path} is not a prop bundle (no {C.MANIFEST})",
            "pass the directory written by prop personalize --out",
        )
    try:  # O_NOFOLLOW: a link put there since the check above is refused, not read
        raw = read(path, C.MANIFEST)
    except OSError as e:
        raise PropError(
            f"bundle {path}: {C.MANIFEST} cannot be read ({e.strerror})", "check its permissions"
        ) from None
    manifest = schema.parse(raw, str(path))
    check_tree(path, manifest)
    return manifest


CODE_SUFFIXES = (".py", ".pyc", ".pyo", ".pyw", ".pyd", ".so")  # files Python would import
MAX_JSON = 256 << 20  # a carried JSON file read whole (a large model's tokenizer.json: tens of MiB)


def check_tree(path: Path, manifest: dict) -> None:
    """What a bundle folder holds, before anything in it is read: plain files and folders only, no
    symbolic link anywhere (prop would read, write or delete through it, outside the bundle); and in
    each folder the manifest lists files in (a LeRobot policy's ``lerobot/`` with its VLM's ``vlm/`` or
    pi0's ``tokenizer/``, which LeRobot and transformers read by name, whatever is there) only listed
    files, none of them code: no Python file, no JSON with an ``auto_map``. Prop never writes any of
    these, so each is refused in one line naming it, ``--trust-remote-code`` or not (that flag trusts
    the import paths a manifest names, never code carried in a bundle's files)."""
    listed = set(manifest[C.M_FILES])
    carried = {n.split("/", 1)[0] for n in listed if "/" in n}
    # Each folder listed once, its entries' types from the listing (no call per file: a sealed bundle's
    # users/ may hold 10,000 records), in the order os.walk would visit them.
    todo = [""]
    while todo:
        rel = todo.pop()
        try:
            with os.scandir(path / rel if rel else path) as it:
                entries = sorted(it, key=lambda e: e.name)
        except OSError:  # gone, or not readable: as os.walk, nothing to read there
            continue
        files, dirs = [], []
        for e in entries:
            name = f"{rel}/{e.name}" if rel else e.name
            try:
                if e.is_symlink():
                    raise link_error(path, Path(e.path))
                if e.is_dir(follow_symlinks=False):
                    dirs.append(name)
                elif e.is_file(follow_symlinks=False):
                    files.append(name)
                else:
                    raise _tampered(path, name, "is neither a file nor a folder")
            except FileNotFoundError:  # gone since the folder was listed: nothing to read there
                continue
        todo.extend(reversed(dirs))
        if rel and rel.split("/", 1)[0] in carried:
            for name in files:
                _check_carried(path, name, listed)
    for name in sorted(listed):
        if name.lower().endswith(CODE_SUFFIXES):
            raise _tampered(path, name, "is code (a bundle never carries code)")


def _check_carried(path: Path, name: str, listed: set[str]) -> None:
    """One file of a folder a library reads by name: listed, and not code."""
    if name not in listed:
        raise _tampered(path, name, f"is not listed in {C.MANIFEST}, and its folder is read by name")
    if name.lower().endswith(CODE_SUFFIXES):
        raise _tampered(path, name, "is code (a bundle never carries code)")
    if name.lower().endswith(".json"):
        try:  # from the bundle folder's descriptor, no part below it followed if it is a link
            raw = read(path, name, limit=MAX_JSON + 1)
        except OSError:
            return  # its sha256 is checked next
        if len(raw) > MAX_JSON:
            raise _tampered(path, name, f"is over {MAX_JSON >> 20} MiB, more than any JSON file prop carries")
        try:
            doc = json.loads(raw)
        except (ValueError, RecursionError):
            return  # its sha256 is checked next; a library that reads it reports what is wrong
        if adapters.names_code(doc):
            raise _tampered(path, name, f"has an {adapters.CODE_FIELD} (code for transformers to import)")


def _tampered(path: Path, name: str, what: str) -> PropError:
    return PropError(f"bundle {path}: {shown(name)} {what}: {TAMPERED}", RESTORE)


@dataclass
class Bundle:
    """A loaded bundle: its manifest, the base module (``loaded``) and its mode, which turns keys into
    behaviour (``modes.Unsealed``: the key encoder; ``modes.Sealed``: the encrypted records)."""

    path: Path
    manifest: dict
    loaded: LoadedModel
    mode: Mode
    arch: str | None = None  # the user's --arch of this command, building the base instead of model.arch

    @property
    def keyed(self) -> KeyedModel | None:
        """Unsealed: the base with its key encoder; sealed: None (there is no encoder)."""
        return self.mode.keyed

    @property
    def is_sealed(self) -> bool:
        """Whether the bundle is sealed (``Mode.is_sealed``: the one name for it)."""
        return self.mode.is_sealed

    @property
    def records(self) -> SealedState | None:
        """Sealed: the payload layout and the encrypted records; unsealed: None."""
        return self.mode.state

    @property
    def layer_names(self) -> list[str]:
        return self.mode.layer_names

    @property
    def parameters(self) -> int:
        return self.mode.parameters(self.loaded)

    @property
    def task(self) -> str:
        return self.manifest[C.M_TASK]

    @property
    def key_bits(self) -> int:
        return int(self.manifest[C.M_KEY]["bits"])

    @property
    def key_encoding(self) -> str:
        # Sealed bundles have no encoder and record none; the audit's blank encoder hashes like the default.
        return self.manifest[C.M_KEY].get("encoding", C.KEY_ENCODINGS[0])

    def check_key(self, key: np.ndarray, what: str = "the key") -> np.ndarray:
        if len(key) != self.key_bits:
            raise PropError(
                f"{what} has {len(key)} bits but the bundle expects {self.key_bits}",
                "use the key the bundle was personalized with",
            )
        return key


def load_bundle(
    path: Path, *, trust_remote_code: bool = False, arch: str | None = None, allow_rollback: bool = False
) -> Bundle:
    """Load and verify (format version, manifest schema and digest, sha256 of every file) a bundle.

    A bundle is data: code its manifest or files name (a module adapter's ``model.arch``, a folder's
    factory, LeRobot processor steps LeRobot does not register) is imported only with
    ``trust_remote_code``; without it such a bundle is refused before anything is imported. ``arch``
    (``--arch``): the user's own factory for a module or folder bundle, called instead of the recorded
    one (their consent, as on personalize; relative paths are from the folder prop runs in).
    ``allow_rollback`` (``--allow-rollback``): a key runs this copy even where it is older than one this
    machine has seen (``rollback``), with a warning; without it, such a key is refused."""
    path = Path(path)
    manifest = read_manifest(path)
    check_files(path, manifest)
    spec = manifest[C.M_MODEL]
    adapters.check_arch_applies(spec, str(path), arch)
    if arch is None:
        adapters.require_trust(adapters.remote_code(spec, str(path)), f"bundle {path}", trust_remote_code)
    # Memory stays within the files' sizes: the weights are read as they lie on disk (safetensors only)
    # and every size the manifest claims is checked against them before anything is built from it.
    weights = adapters.read_weights(path / C.BASE_WEIGHTS, safetensors_only=True)[0]
    loaded = adapters.rebuild(spec, weights, str(path), trust_remote_code=trust_remote_code, arch=arch)
    check_input_shape(manifest, loaded, path)
    return Bundle(path, manifest, loaded, load_mode(path, manifest, loaded, allow_rollback), arch)


# The most numbers one input sample may hold where the model does not fix its input shape (a module or
# folder built by code): 64 MB in float32, so that a manifest cannot make a command allocate gigabytes.
MAX_INPUT = 1 << 24


def check_input_shape(manifest: dict, loaded: LoadedModel, path: Path) -> None:
    """The input shape the manifest records is the model's own where the model fixes it, and bounded
    where it does not (commands allocate inputs of that shape: exports, their verification)."""
    shape = manifest[C.M_IO]["input_shape"]
    if not isinstance(shape, list):
        return  # a policy's features: its own config says their shapes
    where = f"{C.M_IO}.input_shape"
    if loaded.input_shape is not None and tuple(shape) != tuple(loaded.input_shape):
        raise schema.field_error(
            str(path), where, f"is {shape} but the model takes {list(loaded.input_shape)}"
        )
    if math.prod(shape) > MAX_INPUT:
        raise schema.field_error(
            str(path), where, f"is {shape}: {math.prod(shape)} numbers a sample (most: {MAX_INPUT})"
        )


def check_files(path: Path, manifest: dict) -> None:
    """Every file the manifest lists is there and has the sha256 the manifest records, each read from
    the bundle folder's descriptor with no part below it followed if it is a link (``files.opened``)."""
    for name, digest in manifest[C.M_FILES].items():
        try:
            got = sha256_inside(path, name)
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            got = None
        if got is None:
            raise PropError(f"bundle {path} is missing {name}", "write the bundle again")
        if digest != got:
            raise PropError(
                f"bundle {path}: {name} does not match its sha256 in {C.MANIFEST} (modified or corrupt)",
                "restore the bundle from a trusted copy",
            )


def rebuild_original(bundle: Bundle, path: str, trust_remote_code: bool = False) -> LoadedModel:
    """The checkpoint at ``path`` (the original, `--original`) rebuilt the way ``bundle``'s base is: the
    bundle's recorded model spec with that checkpoint's weights, so no flag has to be given again (the
    bundle's ``--arch``, if the user gave one, builds it too)."""
    from prop_adapters.hub import resolve_checkpoint

    spec = bundle.manifest[C.M_MODEL]
    adapter = adapters.adapter_named(spec.get("adapter"), str(bundle.path))
    weights = adapter.weights(Path(resolve_checkpoint(path)))
    try:
        return adapters.rebuild(
            spec, weights, str(path), trust_remote_code=trust_remote_code, arch=bundle.arch
        )
    except (RuntimeError, KeyError, ValueError) as e:
        raise PropError(
            f"--original {path} does not fit the bundle's model ({type(e).__name__})",
            "pass the checkpoint the bundle was personalized from",
        ) from None


def load_sealed(
    bundle_path: Path, command: str, trust_remote_code: bool = False, arch: str | None = None
) -> Bundle:
    """A sealed bundle for a command that only sealed bundles take (add-user, remove-user)."""
    bundle = load_bundle(bundle_path, trust_remote_code=trust_remote_code, arch=arch)
    bundle.mode.require_independent_users(command, bundle_path)
    return bundle
