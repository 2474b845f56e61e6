"""The bundle prop writes and reads: its format (``manifest``), how it is read (``read``) and written
(``write``), its mode (``modes``: a key encoder, or encrypted records kept by ``records`` under
``cipher``), and running it (``runtime``). Nothing here trains: training is ``prop_cli.train``."""

from .read import Bundle, check_files, load_bundle, read_manifest
from .runtime import KeyedPolicy, WrongKeyWarning, run_bundle
from .write import describe_layers, enrol_key, update_manifest, write_sealed, write_unsealed

__all__ = [
    "Bundle",
    "KeyedPolicy",
    "WrongKeyWarning",
    "check_files",
    "describe_layers",
    "enrol_key",
    "load_bundle",
    "read_manifest",
    "run_bundle",
    "update_manifest",
    "write_sealed",
    "write_unsealed",
]


def __getattr__(name: str):
    # The writers of prop 0.1.x (one release, with a warning): write_bundle returned the path.
    import warnings

    from . import write

    old = {"write_bundle": "write_unsealed", "write_sealed_bundle": "write_sealed"}
    if name not in old:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(
        f"prop_cli.bundle.{name} is now prop_cli.bundle.{old[name]} (it returns the manifest written); "
        "the old name goes in prop 0.3",
        DeprecationWarning,
        stacklevel=2,
    )
    if name == "write_sealed_bundle":
        return write.write_sealed

    def write_bundle(out, **kwargs):
        write.write_unsealed(out, **{"keys": [], **kwargs})  # no users enrolled: keys run the base
        return out

    return write_bundle
