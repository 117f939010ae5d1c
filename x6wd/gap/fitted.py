"""What every fitter returns, and the memo that lets the candidates of a round share one
expensive fit of the baseline.

:class:`Fit` is a fitted effect layer (any of :mod:`sim_backend.effects`, GPS or compass)
with the standard errors of its parameters; :class:`IdentityCache` keeps the last few results
of a fit keyed on the identity of the series it was given.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class IdentityCache(Generic[T]):
    """The last few results of an expensive fit, keyed on the identity of the series it was
    given (plus ``extra``): the candidates of a round all fit against one baseline. Each entry
    keeps its series alive, so their ids cannot be reused while it exists."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.entries: list[tuple[tuple[Any, ...], list[Any], T]] = []

    def get(self, series: Sequence[Any], extra: tuple[Any, ...], compute: Callable[[], T]) -> T:
        key = (*(id(s) for s in series), *extra)
        for k, _keep, value in self.entries:
            if k == key:
                return value
        value = compute()
        self.entries.append((key, list(series), value))
        del self.entries[: -self.size]
        return value


@dataclass(frozen=True)
class Fit:
    """A fitted effect: the layer, its parameters as a table, standard errors (same keys)."""

    effect: Any
    se: dict[str, float] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return str(self.effect.name)

    @property
    def params(self) -> dict[str, Any]:
        return {k: v for k, v in self.effect.to_params().items() if k != "name"}
