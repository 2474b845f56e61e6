"""Reproduce the paper's experiments (Section "Experimental Validation", Fig. 4 and Fig. "cap", and the
simulated "User Study").

    python -m examples.reproduce il|digits|reach|capacity|kitchen|all [--quick] [--out DIR]

One module per experiment (``il``, ``digits``, ``capacity``, ``reach``, ``kitchen``); ``baselines``
holds the key-as-input MLP and the state-conditioned CVAE, trained with prop's Eq. 8 key sampling;
``table`` prints the Fig.-4-style table and draws its PNG. Results and commands: ``examples/RESULTS.md``.
"""
