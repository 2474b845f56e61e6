"""`prop attack`: the audit (``audit``), what it attacks for each mode and kind of model (``target``),
its probes (``probes``: one file each, a registry) and the report's table, plot and manifest summary
(``report``)."""

from .audit import apply_max_leak, audit, leak_failures

__all__ = ["apply_max_leak", "audit", "leak_failures"]
