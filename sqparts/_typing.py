"""Shared jaxtyping aliases for sqparts signatures, and the immutability of its results."""

import dataclasses
import types
from collections.abc import Mapping

import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

__all__ = ["Array", "ArrayLike", "Bool", "Float", "Int", "PRNGKeyArray", "freeze_fields"]


class ReadOnlyDict(Mapping):
    """A read-only mapping over a private copy of a dict: a result's dicts (timings, per-part
    statistics). Unlike ``types.MappingProxyType`` it pickles and deep-copies, so results
    go through ``pickle``, ``copy.deepcopy`` and process pools."""

    __slots__ = ("_items",)

    def __init__(self, items=()):
        self._items = dict(items)

    def __getitem__(self, key):
        return self._items[key]

    def __iter__(self):
        return iter(self._items)

    def __len__(self):
        return len(self._items)

    def __repr__(self):
        return repr(self._items)

    def __reduce__(self):
        return (type(self), (self._items,))


def freeze_fields(result) -> None:
    """Make a frozen dataclass's fields immutable as well (immutable results: what it was
    made from stays the maker's to change): arrays become read-only views, dicts read-only
    mappings (:class:`ReadOnlyDict`) and lists tuples, all the way down (a list of
    per-part dicts: a tuple of read-only mappings). Other values are kept as they are."""
    for field in dataclasses.fields(result):
        value = getattr(result, field.name)
        frozen = _frozen(value)
        if frozen is not value:
            object.__setattr__(result, field.name, frozen)


def _frozen(value):
    if isinstance(value, np.ndarray):
        if not value.flags.writeable:
            return value
        view = value.view()
        view.flags.writeable = False
        return view
    if isinstance(value, ReadOnlyDict):
        return value
    if isinstance(value, (dict, types.MappingProxyType)):
        return ReadOnlyDict({k: _frozen(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):  # not a named tuple
        items = [_frozen(v) for v in value]
        return value if isinstance(value, tuple) and all(a is b for a, b in zip(items, value)) else tuple(items)
    return value
