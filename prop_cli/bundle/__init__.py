"""The bundle prop writes and reads: its format (``manifest``), how it is read (``read``) and written
(``write``), its mode (``modes``: a key encoder, or encrypted records kept by ``records`` under
``cipher``). Nothing here trains (``prop_cli.train``) or runs a bundle (``prop_cli.run``)."""

from .read import Bundle, check_files, load_bundle, read_manifest
from .write import describe_layers, enrol_key, update_manifest, write_sealed, write_unsealed

__all__ = [
    "Bundle",
    "check_files",
    "describe_layers",
    "enrol_key",
    "load_bundle",
    "read_manifest",
    "update_manifest",
    "write_sealed",
    "write_unsealed",
]

