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

