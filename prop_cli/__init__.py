"""prop: add private keys to existing neural-network checkpoints (PRoP)."""

from . import compat

__version__ = "0.1.0"

compat.install()  # the import paths of 0.1.x, for one release (prop_cli.compat)
