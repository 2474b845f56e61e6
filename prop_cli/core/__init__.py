"""The method itself, independent of any file format: where keys come from (``key_files``: key files and
passphrases; ``passphrase``: their strength), drawing other keys (``key_sampling``: random keys, Hamming
neighbours), the keyed model of Eq. 5 (``keyed_model``), which layers to key (``layers``,
``batch_axes``), sealed payloads (``payload``), the shared metrics (``metrics``), the compute device
(``device``), and the vocabulary JSON files' schemas are written in (``rules``: the bundle format's, each
adapter's model spec)."""
