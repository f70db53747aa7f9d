"""One registry mechanism for everything chosen by name: resamplers, likelihoods, filters, motion priors.

A :class:`Registry` maps lower-case names to objects (functions, classes or factories). Code inside the
library registers with the :meth:`Registry.register` decorator; outside packages register through a
``importlib.metadata`` entry-point group (loaded lazily on first lookup), which is how ``priors`` offers its
motion priors to ``torchpf`` without ``torchpf`` importing ``priors``. A source checkout run without being
installed has no metadata: its ``pyproject.toml`` then lists the group (:func:`checkout_entry_points`). A
lookup of an unknown name raises a ``ValueError`` that lists the registered names, so a CLI can print it as a
one-line error.

Example::

    from torchpf.registry import Registry
    SHAPES = Registry("shape")

    @SHAPES.register("disc")
    def disc(radius): ...

    SHAPES.get("disc")        # -> disc;  SHAPES.get("blob") -> ValueError: unknown shape 'blob'; choose ...
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Any, Generic, TypeVar

T = TypeVar("T")

#: the pyproject.toml of a source checkout that holds this package
_PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def checkout_entry_points(group: str, pyproject: str | Path = _PYPROJECT) -> dict[str, EntryPoint]:
    """The ``group`` entry points that torchpf's own ``pyproject.toml`` declares, for code run from a source
    checkout that was never installed (``PYTHONPATH=.``, a notebook beside the sources, a copy on a GPU
    machine): there no package metadata lists them. ``{}`` when ``pyproject`` is absent, is another project's,
    or cannot be read (Python 3.10 has no ``tomllib``)."""
    try:
        import tomllib

        data = tomllib.loads(Path(pyproject).read_text(encoding="utf-8"))
    except (ImportError, OSError, ValueError):
        return {}
    project = data.get("project", {})
    if project.get("name") != "torchpf":
        return {}
    table = project.get("entry-points", {}).get(group, {})
    return {name.lower(): EntryPoint(name, value, group) for name, value in table.items()}


class Registry(Mapping[str, T], Generic[T]):
    """Name -> object table of one kind (``kind`` names it in error messages).

    Args:
        kind: what the entries are, for messages (``"resampler"``, ``"likelihood"``).
        entry_point_group: optional entry-point group whose entries are added, unloaded, on first lookup
            (``entry.load()`` runs when the name is first used).
        aliases: extra names for registered entries (``{"condensation": "sir"}``).
    """

    def __init__(self, kind: str, entry_point_group: str | None = None, aliases: Mapping[str, str] = ()):
        self.kind = kind
        self.entry_point_group = entry_point_group
        self._entries: dict[str, T] = {}
        self._entry_points: dict[str, Any] | None = None if entry_point_group else {}
        self._aliases = {k.lower(): v.lower() for k, v in dict(aliases).items()}

    # ------------------------------------------------------------------ registering
    def register(self, name: str, obj: T | None = None, *, replace: bool = False):
        """Register ``obj`` under ``name`` (lower-cased); without ``obj``, a decorator that does so."""

        def add(value: T) -> T:
            key = name.lower()
            if not replace and (key in self._entries or key in self._aliases):
                raise ValueError(f"a {self.kind} named {name!r} is already registered")
            self._entries[key] = value
            return value

        return add if obj is None else add(obj)

    def unregister(self, name: str) -> T:
        """Remove and return the entry registered as ``name`` (a ``KeyError`` if there is none)."""
        return self._entries.pop(name.lower())

    # ------------------------------------------------------------------ lookup
    def _outside(self) -> dict[str, Any]:
        if self._entry_points is None:
            found = {ep.name.lower(): ep for ep in entry_points(group=self.entry_point_group)}
            # an installed torchpf lists its entry points in its metadata; a bare checkout, in its pyproject
            self._entry_points = found or checkout_entry_points(self.entry_point_group)
        return self._entry_points

    def _key(self, name: str) -> str:
        key = name.lower()
        return self._aliases.get(key, key)

    def __getitem__(self, name: str) -> T:
        key = self._key(name)
        if key not in self._entries:
            outside = self._outside()
            if key not in outside:
                raise KeyError(name)
            self._entries[key] = outside[key].load()
        return self._entries[key]

    def get(self, name: str, default: Any = None) -> T:  # type: ignore[override]
        """The entry called ``name`` (case-insensitive, aliases followed); an unknown name raises
        ``ValueError`` naming the registered ones (``default`` is accepted for ``Mapping`` compatibility and
        returned instead when given)."""
        try:
            return self[name]
        except KeyError:
            if default is not None:
                return default
            if not self.names() and self.entry_point_group:
                raise ValueError(
                    f"unknown {self.kind} {name!r}: none is registered. They come from the "
                    f"{self.entry_point_group!r} entry points of an installed torchpf: pip install torchpf "
                    "(or pip install -e . in a checkout)"
                ) from None
            raise ValueError(f"unknown {self.kind} {name!r}; choose from {self.names()}") from None

    def canonical(self, name: str) -> str:
        """The registered name that ``name`` stands for (case-insensitive, aliases followed); an unknown name
        raises the ``ValueError`` of :meth:`get`."""
        self.get(name)
        return self._key(name)

    def resolve(self, spec: str | T) -> T:
        """``spec`` itself when it is not a string, else the entry it names (see :meth:`get`)."""
        return self.get(spec) if isinstance(spec, str) else spec

    def names(self, aliases: bool = False) -> list[str]:
        """Sorted registered names (with the aliases when ``aliases``)."""
        names = set(self._entries) | set(self._outside())
        if aliases:
            names |= set(self._aliases)
        return sorted(names)

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and (
            self._key(name) in self._entries or self._key(name) in self._outside()
        )

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self.names())

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {self.names()})"


Factory = Callable[..., Any]
