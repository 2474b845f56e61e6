"""The method itself, independent of any file format: keys and key spaces (``keys``, ``keyspace``), the
keyed model of Eq. 5 (``keyed``), which layers to key (``layers``, ``batch_axes``), sealed payloads
(``payload``), the shared metrics (``metrics``) and the compute device (``device``)."""
