"""Stage outputs as JSON and arrays, for the stage cache: a format that can never run code.

A value is written as JSON whose arrays are stored apart (``.npy`` members of a zip, read with
``allow_pickle=False``). Dataclasses, pydantic models and enums are named by module and class and
rebuilt only from classes already imported into this process: reading an entry never imports a
module. A value that is one of the stage's inputs (``SaliencyMap.bev`` is the IPM's ``Bev``) is
written as a reference to that input, not copied.
"""

from __future__ import annotations

import dataclasses
import enum
import sys
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from pydantic import BaseModel

from sgf_pipeline.errors import DataError

#: Stores an array under a name and returns that name.
ArraySink = Callable[[np.ndarray], str]
#: Returns the array stored under a name.
ArraySource = Callable[[str], np.ndarray]


class NotCacheableError(DataError):
    """A value the stage cache cannot write (an object that is neither data nor a known class)."""


def _class_name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _loaded_class(name: str) -> type:
    """The class named ``module:qualname``, from a module already imported (none is imported here)."""
    module_name, _, qualname = name.partition(":")
    module = sys.modules.get(module_name)
    if module is None:
        raise DataError(f"the cache names class {name}, whose module is not loaded")
    obj: Any = module
    for part in qualname.split("."):
        obj = getattr(obj, part, None)
    if not isinstance(obj, type) or not (dataclasses.is_dataclass(obj) or issubclass(obj, (BaseModel, enum.Enum))):
        raise DataError(f"the cache names {name}, which is not a dataclass, model or enum")
    return obj


def encode(value: Any, sink: ArraySink, inputs: Mapping[int, str] | None = None) -> Any:
    """``value`` as JSON-ready data; arrays go to ``sink``; inputs (by ``id``) become references."""
    refs = inputs or {}

    def enc(v: Any) -> Any:
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        if id(v) in refs and (isinstance(v, np.ndarray) or dataclasses.is_dataclass(v)):
            return {"r": refs[id(v)]}
        if isinstance(v, np.ndarray):
            if v.dtype.hasobject:
                raise NotCacheableError(f"an array of Python objects ({v.dtype}) cannot be cached")
            return {"a": sink(v)}
        if isinstance(v, np.generic):
            return {"a": sink(np.asarray(v)), "s": 1}
        if isinstance(v, enum.Enum):
            return {"e": _class_name(type(v)), "v": enc(v.value)}
        if isinstance(v, tuple) and not hasattr(v, "_fields"):
            return {"t": [enc(x) for x in v]}
        if isinstance(v, list):
            return [enc(x) for x in v]
        if isinstance(v, (set, frozenset)):
            return {"set": [enc(x) for x in sorted(v, key=repr)], "frozen": isinstance(v, frozenset)}
        if isinstance(v, Mapping):
            if all(isinstance(k, str) for k in v):
                return {"d": {k: enc(x) for k, x in v.items()}}
            return {"p": [[enc(k), enc(x)] for k, x in v.items()]}
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            fields = {f.name: enc(getattr(v, f.name)) for f in dataclasses.fields(v)}
            return {"c": _class_name(type(v)), "f": fields}
        if isinstance(v, BaseModel):
            return {"m": _class_name(type(v)), "f": enc(v.model_dump(mode="python"))}
        raise NotCacheableError(f"a {type(v).__module__}.{type(v).__qualname__} cannot be cached")

    return enc(value)


def decode(data: Any, source: ArraySource, inputs: Mapping[str, Any] | None = None) -> Any:
    """The value :func:`encode` wrote; references resolve to ``inputs`` by name."""
    refs = inputs or {}

    def dec(d: Any) -> Any:
        if d is None or isinstance(d, (bool, int, float, str)):
            return d
        if isinstance(d, list):
            return [dec(x) for x in d]
        if not isinstance(d, dict):
            raise DataError(f"unreadable cache value {d!r:.60}")
        if "a" in d:
            array = source(d["a"])
            return array[()] if d.get("s") else array
        if "r" in d:
            if d["r"] not in refs:
                raise DataError(f"the cache refers to input {d['r']!r}, which this stage does not have")
            return refs[d["r"]]
        if "t" in d:
            return tuple(dec(x) for x in d["t"])
        if "d" in d:
            return {k: dec(x) for k, x in d["d"].items()}
        if "p" in d:
            return {_hashable(dec(k)): dec(x) for k, x in d["p"]}
        if "set" in d:
            items = [_hashable(dec(x)) for x in d["set"]]
            return frozenset(items) if d["frozen"] else set(items)
        if "e" in d:
            return _loaded_class(d["e"])(dec(d["v"]))
        if "c" in d:
            cls = _loaded_class(d["c"])
            values = {k: dec(x) for k, x in d["f"].items()}
            init = {f.name for f in dataclasses.fields(cls) if f.init}
            obj = cls(**{k: v for k, v in values.items() if k in init})
            for k, v in values.items():
                if k not in init:
                    object.__setattr__(obj, k, v)
            return obj
        if "m" in d:
            model = _loaded_class(d["m"])
            assert issubclass(model, BaseModel)
            return model.model_validate(dec(d["f"]))
        raise DataError(f"unreadable cache value {d!r:.60}")

    return dec(data)


def _hashable(value: Any) -> Any:
    return tuple(_hashable(v) for v in value) if isinstance(value, list) else value
