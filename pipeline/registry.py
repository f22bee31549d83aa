"""One tiny registry class, one instance per plug-in family (features, estimators, pre-filters).

    EXTRACTORS = Registry("feature")
    @EXTRACTORS.register("sift")
    class SIFT(Extractor): ...
    EXTRACTORS.get("sift")          # -> class, or ImtuneError naming the unknown name
    EXTRACTORS.availability()       # -> {name: (available, reason)} for `tune list`
"""
from __future__ import annotations

import difflib
from collections.abc import Callable, Iterable

from pipeline.errors import ImtuneError, UnavailableError


def close_matches(name: str, names: Iterable[str], n: int = 3) -> list[str]:
    """Up to ``n`` of ``names`` that look like ``name`` (difflib ratio >= 0.6; case-insensitive), best first."""
    names = [str(x) for x in names]
    by_lower: dict[str, str] = {}
    for x in names:
        by_lower.setdefault(x.lower(), x)
    hits = difflib.get_close_matches(str(name).lower(), list(by_lower), n=n, cutoff=0.6)
    return [by_lower[h] for h in hits]


def did_you_mean(name: str, names: Iterable[str]) -> str:
    """`` (did you mean 'sift'?)`` / `` (did you mean 'sift' or 'rootsift'?)``, or "" when nothing is close."""
    hits = close_matches(name, names)
    if not hits:
        return ""
    return " (did you mean " + " or ".join(repr(h) for h in hits) + "?)"


class Registry:
    def __init__(self, kind: str):
        self.kind = kind
        self._items: dict[str, object] = {}
        self._describe: dict[str, str] = {}
        self._resolvers: list[Callable] = []

    def register(self, name: str, description: str = "") -> Callable:
        def deco(obj):
            if name in self._items:
                raise ValueError(f"{self.kind} {name!r} registered twice")
            self._items[name] = obj
            self._describe[name] = description or (obj.__doc__ or "").strip().splitlines()[0] if (obj.__doc__ or description) else ""
            return obj
        return deco

    def names(self) -> list[str]:
        return list(self._items)

    def __contains__(self, name: str) -> bool:
        return name in self._items

    def add_resolver(self, fn: Callable) -> None:
        """``fn(name)`` -> an object for a name that is not registered (e.g. a composed feature name
        ``det+aff+desc`` or ``custom:DIR``), or None to decline; it may raise ImtuneError for a name it
        recognises but rejects. Consulted by ``get`` in the order added."""
        self._resolvers.append(fn)

    def get(self, name: str):
        if name not in self._items:
            for fn in self._resolvers:
                obj = fn(name)
                if obj is not None:
                    return obj
            raise ImtuneError(f"unknown {self.kind} {name!r}{did_you_mean(name, self._items)} "
                              f"(known: {', '.join(sorted(self._items))})")
        return self._items[name]

    def description(self, name: str) -> str:
        return self._describe.get(name, "")

    def availability(self) -> dict[str, tuple[bool, str]]:
        """name -> (available, reason). An entry is available if its ``check_available()`` returns
        without raising; the reason is the UnavailableError message otherwise."""
        out = {}
        for name, obj in self._items.items():
            check = getattr(obj, "check_available", None)
            try:
                if check is not None:
                    check()
                out[name] = (True, "")
            except UnavailableError as e:
                out[name] = (False, str(e))
        return out
