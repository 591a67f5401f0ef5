"""State dicts of the classes that live across frames, their encoding as JSON and arrays, and nested-dict helpers
(the lowest layer: imports no stage).

:func:`encode_state` turns a state (nested dicts, lists, tuples, sets, str/int/float/bool/None, numpy arrays and
scalars, torch tensors, and objects of the types a :class:`StateTypes` registry names) into a JSON-able tree plus
named arrays; :func:`decode_state` rebuilds it from those. Decoding creates objects only of the registry's types
(never of a type named by the data), so a crafted tree can give wrong values but cannot run code. An object, list,
dict, set, array or tensor met twice is encoded once and referenced after, so objects shared between parts of a
state (a keyframe in the map and the frontend's reference to it) are shared again after decoding.

Tree nodes: JSON null/true/false/numbers/strings stand for themselves (floats as Python's json writes them: NaN
and Infinity included); every other node is a JSON object whose
first key is its tag: ``$list``, ``$tuple``, ``$set``, ``$frozenset``, ``$dict`` (with ``items``: [key, value]
pairs, keys of any type), ``$array``/``$tensor`` (a name among the arrays), ``$scalar`` (a numpy scalar: dtype
and ``value``), ``$enum`` (type and member ``name``), ``$object`` (type and ``fields``), ``$ref`` (the ``$id`` of a
node met before).
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import sys
from typing import Any, Callable, Iterable, Mapping

import numpy as np

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
                              f"it was written by another tambridge version: run again with --overwrite instead of --resume")
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


# ---- encoding states as JSON and arrays -----------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class StateCodec:
    """How a type without plain attributes is stored: ``encode(obj)`` -> dict of encodable parts by name,
    ``decode(parts)`` -> a new object."""

    cls: type
    encode: Callable[[Any], dict[str, Any]]
    decode: Callable[[dict[str, Any]], Any]


class StateTypes:
    """The registry of the types a state may hold beyond the built-in ones, each under its class name.

    ``records``: classes stored as their attributes (a dataclass: its fields) and rebuilt without calling their
    constructor; ``enums``: enum classes, stored by member name; ``codecs``: :class:`StateCodec` for the rest.
    """

    def __init__(self, records: Iterable[type] = (), enums: Iterable[type[enum.Enum]] = (),
                 codecs: Iterable[StateCodec] = ()) -> None:
        self.by_type: dict[type, type | StateCodec] = {}
        self.by_name: dict[str, type | StateCodec] = {}
        for entry in (*records, *enums, *codecs):
            cls = entry.cls if isinstance(entry, StateCodec) else entry
            if cls.__qualname__ in self.by_name:
                raise ValueError(f"two state types named {cls.__qualname__}")
            self.by_type[cls] = self.by_name[cls.__qualname__] = entry


class _Unencodable(TypeError):
    """A value of a type a state may not hold; ``where`` is the path to it, filled in on the way out."""

    def __init__(self, kind: type) -> None:
        super().__init__()
        self.kind = kind
        self.where: list[str] = []

    def __str__(self) -> str:
        return (f"cannot store a {self.kind.__module__}.{self.kind.__qualname__} in a state "
                f"(at {'/'.join(self.where) or 'the top'}): it is not in the registry of state types")


_ATOMS = (type(None), bool, int, float, str)
_DICTS = {dict: "dict", collections.OrderedDict: "OrderedDict", collections.Counter: "Counter"}
_SCALAR_KINDS = "biuf"  # numpy bool, signed and unsigned integer, float scalars


def _field_values(value: object) -> dict[str, Any]:
    """A record's attributes: a dataclass's fields, else its instance attributes."""
    if dataclasses.is_dataclass(value):
        return {field.name: getattr(value, field.name) for field in dataclasses.fields(value)}
    return dict(vars(value))


class _Encoder:
    def __init__(self, types: StateTypes) -> None:
        self.types = types
        self.arrays: dict[str, np.ndarray] = {}
        # id -> (the object, what a second occurrence encodes to); holding the object keeps its id from being reused
        # by a temporary made later in the same pass.
        self._memo: dict[int, tuple[object, dict]] = {}
        self._torch = sys.modules.get("torch")  # no tensor can exist unless torch is imported

    def _identified(self, value: object, node: dict) -> dict:
        """``node`` with a fresh ``$id``; later occurrences of ``value`` become references to it."""
        node["$id"] = ident = len(self._memo)
        self._memo[id(value)] = (value, {"$ref": ident})
        return node

    def _array(self, tag: str, value: object, array: np.ndarray, **extra) -> dict:
        if array.dtype.hasobject:
            raise _Unencodable(type(value))
        name = f"a{len(self.arrays)}"
        self.arrays[name] = array
        node = {tag: name, **extra}
        self._memo[id(value)] = (value, node)
        return node

    def _items(self, values: Iterable, keys: Iterable) -> list:
        encoded = []
        for key, item in zip(keys, values):
            try:
                encoded.append(self.encode(item))
            except _Unencodable as error:
                error.where.insert(0, str(key))
                raise
        return encoded

    def encode(self, value: Any) -> Any:
        kind = type(value)
        if kind in _ATOMS:
            return value
        seen = self._memo.get(id(value))
        if seen is not None:
            return seen[1]
        if kind is list:
            node = self._identified(value, {"$list": None})
            node["$list"] = self._items(value, range(len(value)))
            return node
        if kind is tuple:
            return {"$tuple": self._items(value, range(len(value)))}
        if kind in _DICTS:
            node = self._identified(value, {"$dict": _DICTS[kind], "items": None})
            keys = list(value)
            node["items"] = [list(pair) for pair in zip(self._items(keys, keys), self._items(value.values(), keys))]
            return node
        if kind is set:
            node = self._identified(value, {"$set": None})
            node["$set"] = self._items(value, value)
            return node
        if kind is frozenset:
            return {"$frozenset": self._items(value, value)}
        if kind is np.ndarray:
            return self._array("$array", value, value)
        if isinstance(value, np.generic) and value.dtype.kind in _SCALAR_KINDS:
            return {"$scalar": value.dtype.name, "value": value.item()}
        if self._torch is not None and kind is self._torch.Tensor:
            return self._array("$tensor", value, value.detach().cpu().numpy(), requires_grad=value.requires_grad)
        entry = self.types.by_type.get(kind)
        if entry is None:
            raise _Unencodable(kind)
        if isinstance(value, enum.Enum):
            return {"$enum": kind.__qualname__, "name": value.name}
        parts = entry.encode(value) if isinstance(entry, StateCodec) else _field_values(value)
        node = self._identified(value, {"$object": kind.__qualname__, "fields": None})
        node["fields"] = dict(zip(parts, self._items(parts.values(), parts)))
        return node


def encode_state(value: Any, types: StateTypes) -> tuple[Any, dict[str, np.ndarray]]:
    """``value`` as (a JSON-able tree, its arrays by name); see the module docstring. The arrays are the state's
    own (tensors: views of them on the CPU), not copies: write them out before the state changes.

    Raises TypeError naming the path to a value of a type that neither the format nor ``types`` knows.
    """
    encoder = _Encoder(types)
    return encoder.encode(value), encoder.arrays


class _Decoder:
    def __init__(self, types: StateTypes, arrays: Mapping[str, np.ndarray]) -> None:
        self.types = types
        self.arrays = arrays
        self._objects: dict[int, Any] = {}
        self._loaded: dict[tuple[str, str], Any] = {}
        self._tags = {"$list": self._list, "$tuple": self._tuple, "$dict": self._dict, "$set": self._set,
                      "$frozenset": self._frozenset, "$array": self._array, "$tensor": self._tensor,
                      "$scalar": self._scalar, "$enum": self._enum, "$object": self._object, "$ref": self._ref}

    def decode(self, node: Any) -> Any:
        if type(node) in _ATOMS:
            return node
        if type(node) is not dict or not node:
            raise ValueError(f"unexpected {type(node).__name__} in the state tree")
        tag = next(iter(node))
        if tag not in self._tags:
            raise ValueError(f"unknown state node {tag!r}")
        return self._tags[tag](node)

    def _remember(self, node: dict, value: Any) -> Any:
        ident = node["$id"]
        if type(ident) is not int or ident in self._objects:
            raise ValueError(f"bad or repeated $id {ident!r}")
        self._objects[ident] = value
        return value

    def _sequence(self, items: Any) -> Iterable:
        if type(items) is not list:
            raise ValueError(f"expected a list in the state tree, got {type(items).__name__}")
        return (self.decode(item) for item in items)

    def _list(self, node: dict) -> list:
        value = self._remember(node, [])
        value.extend(self._sequence(node["$list"]))
        return value

    def _tuple(self, node: dict) -> tuple:
        return tuple(self._sequence(node["$tuple"]))

    def _dict(self, node: dict) -> dict:
        kinds = {name: kind for kind, name in _DICTS.items()}
        value = self._remember(node, kinds[node["$dict"]]())
        for pair in self._sequence_of_pairs(node["items"]):
            value[self.decode(pair[0])] = self.decode(pair[1])
        return value

    @staticmethod
    def _sequence_of_pairs(items: Any) -> list:
        if type(items) is not list or any(type(pair) is not list or len(pair) != 2 for pair in items):
            raise ValueError("a $dict's items are not [key, value] pairs")
        return items

    def _set(self, node: dict) -> set:
        value = self._remember(node, set())
        value.update(self._sequence(node["$set"]))
        return value

    def _frozenset(self, node: dict) -> frozenset:
        return frozenset(self._sequence(node["$frozenset"]))

    def _array(self, node: dict) -> np.ndarray:
        key = ("$array", node["$array"])
        if key not in self._loaded:
            array = self.arrays[node["$array"]]
            if type(array) is not np.ndarray or array.dtype.hasobject:
                raise ValueError(f"array {node['$array']!r} is not a plain numpy array")
            self._loaded[key] = array
        return self._loaded[key]

    def _tensor(self, node: dict):
        import torch

        key = ("$tensor", node["$tensor"])
        if key not in self._loaded:
            requires_grad = node["requires_grad"]
            if type(requires_grad) is not bool:
                raise ValueError("a tensor's requires_grad is not a bool")
            array = self._array({"$array": node["$tensor"]})
            self._loaded[key] = torch.from_numpy(array).requires_grad_(requires_grad)
        return self._loaded[key]

    def _scalar(self, node: dict) -> np.generic:
        dtype = np.dtype(node["$scalar"])
        value = node["value"]
        if dtype.kind not in _SCALAR_KINDS or type(value) not in (bool, int, float):
            raise ValueError(f"bad numpy scalar {node['$scalar']!r}: {value!r}")
        return dtype.type(value)

    def _entry(self, name: Any) -> type | StateCodec:
        entry = self.types.by_name.get(name) if type(name) is str else None
        if entry is None:
            raise ValueError(f"type {name!r} is not one a checkpoint may hold")
        return entry

    def _enum(self, node: dict) -> enum.Enum:
        entry = self._entry(node["$enum"])
        if not (isinstance(entry, type) and issubclass(entry, enum.Enum)) or node["name"] not in entry.__members__:
            raise ValueError(f"{node['$enum']!r} has no member {node['name']!r}")
        return entry.__members__[node["name"]]

    def _object(self, node: dict) -> Any:
        entry = self._entry(node["$object"])
        fields = node["fields"]
        if type(fields) is not dict:
            raise ValueError(f"the fields of a {node['$object']} are not a JSON object")
        if isinstance(entry, StateCodec):
            return self._remember(node, entry.decode({name: self.decode(item) for name, item in fields.items()}))
        if issubclass(entry, enum.Enum):
            raise ValueError(f"{node['$object']} is an enum, not an object type")
        if dataclasses.is_dataclass(entry) and set(fields) != {field.name for field in dataclasses.fields(entry)}:
            raise ValueError(f"a {node['$object']} with fields {sorted(fields)}: another version of that type")
        # Made before its fields, so that references back to it from inside them resolve.
        value = self._remember(node, entry.__new__(entry))
        vars(value).update({name: self.decode(item) for name, item in fields.items()})
        return value

    def _ref(self, node: dict) -> Any:
        return self._objects[node["$ref"]]


def decode_state(tree: Any, arrays: Mapping[str, np.ndarray], types: StateTypes) -> Any:
    """The value :func:`encode_state` encoded as ``tree`` and ``arrays`` (arrays are used, not copied; tensors
    share their memory). Builds objects only of the built-in types and those of ``types``.

    Raises ValueError, KeyError or TypeError on a tree that :func:`encode_state` could not have written.
    """
    return _Decoder(types, arrays).decode(tree)
