"""State dicts of the classes that live across frames, and nested-dict helpers (the lowest layer: imports no stage)."""

from __future__ import annotations

from typing import Any, Iterable

from tambridge.errors import CheckpointError


def attribute_state(owner: object, transient: Iterable[str]) -> dict[str, Any]:
    """The instance attributes of ``owner`` except the ``transient`` ones (threads, locks, what the constructor
    rebuilds from its arguments). The values are the owner's own objects, not copies."""
    skipped = set(transient)
    return {name: value for name, value in vars(owner).items() if name not in skipped}


def restore_attributes(owner: object, state: dict[str, Any]) -> None:
    """Set the attributes saved by :func:`attribute_state` on a freshly constructed ``owner``."""
    missing = sorted(set(state) - set(vars(owner)))
    if missing:
        # A checkpoint of the same version always names the same attributes; anything else is a version mismatch.
        raise CheckpointError(f"checkpoint holds attributes {missing} that {type(owner).__name__} does not have; "
                              f"it was written by another tambridge version: run again without --resume")
    vars(owner).update(state)


def dotted_items(values: dict, prefix: str = "") -> dict[str, Any]:
    """Every leaf of a nested dict under its dotted key (``mapper.iterations``), in insertion order."""
    leaves = {}
    for key, value in values.items():
        if isinstance(value, dict):
            leaves.update(dotted_items(value, f"{prefix}{key}."))
        else:
            leaves[f"{prefix}{key}"] = value
    return leaves
