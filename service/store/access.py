"""Who is asking: the principal behind an API key, and what it may see.

Every job and model records the name of the key that created it (its owner). A principal sees
its own, an admin sees everything; stores built for a principal (``viewer``) answer as if the
others' records did not exist, so a stranger's id is a 404, not a 403.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Principal:
    """An authenticated caller: the key's name and whether it is an admin key."""

    name: str
    admin: bool = False

    def can_see(self, owner: str) -> bool:
        return self.admin or owner == self.name


#: The caller when no API keys are configured: one open deployment, everything visible.
ANONYMOUS = Principal("anonymous", admin=True)
