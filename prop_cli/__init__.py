"""prop: add private keys to existing neural-network checkpoints (PRoP)."""

__version__ = "0.2.0"
