"""Training: one recipe per {array model (``array``), policy with its own loss (``policy``)} x
{unsealed, sealed (``sealed_array``, ``sealed_policy``)}, picked by ``choose``; every recipe runs the
same step loop and optimiser stack (``loop``, ``optim``). The objective is ``objective`` (Eq. 8),
``hardening`` adds ``--harden``'s terms, ``report`` is the per-user report personalize prints."""

from .choose import choose, personalize, sealed_recipe, settled
from .recipe import Job, SealedUser, Trained, User, Written

__all__ = [
    "Job", "SealedUser", "Trained", "User", "Written", "choose", "personalize", "sealed_recipe", "settled",
]  # fmt: skip
