"""Registries of strategy objects: what an option such as ``method=``, ``damping=`` or
``linear_solver=`` names.

Each registry holds objects of one base class by their ``name``; an option takes a registered
name or an object of that class. The modules that own a kind of strategy
(:mod:`torchql.schemes`, :mod:`torchql.damping`, :mod:`torchql.propagators`) keep the errors that
name their option.
"""

from __future__ import annotations

__all__ = ["Registry"]


class Registry:
    """Objects of class ``base`` by name.

    Parameters
    ----------
    base : type
        The class every registered object (and every object an option may take) is an instance of.
    public_name : str
        How messages name ``base``, e.g. ``"torchql.schemes.Scheme"``.
    what : str
        How the error of :meth:`register` names what it received, e.g. ``"an iteration scheme"``.
    """

    def __init__(self, base: type, public_name: str, what: str) -> None:
        self.base, self.public_name, self.what = base, public_name, what
        self.entries: dict = {}

    @property
    def names(self) -> tuple:
        """The registered names, in registration order."""
        return tuple(self.entries)

    def register(self, entry):
        """Register ``entry`` under its ``name`` (replacing one of that name); returns it."""
        if not isinstance(entry, self.base):
            raise TypeError(f"{self.what} must be a {self.public_name}; received {type(entry).__name__}")
        self.entries[entry.name] = entry
        return entry

    def find(self, value):
        """``value`` itself when it is a ``base``, the object it names, or ``None``."""
        if isinstance(value, self.base):
            return value
        try:
            return self.entries.get(value)
        except TypeError:  # unhashable: names nothing
            return None
