"""prop: add private keys to existing neural-network checkpoints (PRoP)."""

from . import _moved

__version__ = "0.1.0"

_moved.install()  # the import paths of 0.1.x, for one release (prop_cli._moved)
