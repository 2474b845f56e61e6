"""Deprecated: the checkpoint adapters are ``prop_cli.adapters`` since prop 0.2. This package keeps
``import prop_adapters`` (and its submodules, e.g. ``prop_adapters.base``) working for one release,
with a DeprecationWarning; it goes in prop 0.3."""

import sys

from prop_cli import compat

compat.install()
del sys.modules[__name__]  # the import that runs this file returns the alias imported next
__import__(__name__)
