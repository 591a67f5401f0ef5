"""Declaring a config key: its default, one line of documentation and the values it accepts.

The stage configs declare every key with :func:`setting` (nested sections with :func:`section`), and keys with a
closed set of values as a :class:`Choice`. :mod:`tambridge.config` reads these when a config is loaded, refusing a
bad value with one line naming the key and what it accepts, and ``tambridge config`` prints each key's ``doc``.
A config dataclass may also define ``conflict(self) -> str | None``: a rule between its keys, checked after each
key's own.
"""

from __future__ import annotations

import dataclasses
import enum
import re
from typing import Any, Callable


class Choice(str, enum.Enum):
    """A key's closed set of string values.

    Members are named as their values: they then compare, hash and print as the plain string, so code that
    compares with ``"orb"`` and dicts keyed by the string keep working.
    """

    def __str__(self) -> str:
        return self.value

    @classmethod
    def parse(cls, value: Any) -> Choice | str | None:
        """The member that ``value`` names (case and surrounding spaces ignored), or None."""
        try:
            return cls(str(value).strip().lower())
        except ValueError:
            return None

    @classmethod
    def accepted(cls) -> str:
        """What the key accepts, for error messages and ``tambridge config``."""
        return "one of " + ", ".join(member.value for member in cls)

    @classmethod
    def renamed(cls) -> dict[str, str]:
        """Former values and their new names, so that a refused old value says what to write instead."""
        return {}


class Device(Choice):
    """The values of the config's ``device`` (:func:`tambridge.device.resolve_device`); ``cuda:N`` (GPU N of several)
    is accepted too, as a plain string. Here rather than beside ``Config``, whose module imports torch: the command
    line needs the choices at once."""

    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"

    @classmethod
    def parse(cls, value) -> Device | str | None:
        name = str(value).strip().lower()
        if re.fullmatch(r"cuda:\d+", name):
            return name
        return super().parse(name)

    @classmethod
    def accepted(cls) -> str:
        return super().accepted() + " (or cuda:N)"


@dataclasses.dataclass(frozen=True)
class Range:
    """The numbers a key accepts: an interval, closed unless ``*_open``; None leaves that side unbounded."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def __contains__(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)

    def __str__(self) -> str:
        if self.high is None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        if self.low is None:
            return f"{'<' if self.high_open else '<='} {self.high:g}"
        return f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"


def at_least(low: float) -> Range:
    return Range(low)


POSITIVE = Range(0, low_open=True)
"""> 0."""
NON_NEGATIVE = Range(0)
""">= 0."""
FRACTION = Range(0, 1, low_open=True)
"""(0, 1]: a share that cannot be nothing."""
UNIT = Range(0, 1)
"""[0, 1]."""


def setting(default: Any, doc: str, accepts: Range | None = None) -> Any:
    """A dataclass field for a config key: ``doc`` is one line (unit included), ``accepts`` its numeric range.

    Every float key must also be finite; None (for an optional key) is always accepted.
    """
    return dataclasses.field(default=default, metadata={"doc": doc, "accepts": accepts})


def section(factory: Callable[[], Any], doc: str) -> Any:
    """A dataclass field holding a nested config (a dataclass of settings)."""
    return dataclasses.field(default_factory=factory, metadata={"doc": doc})
