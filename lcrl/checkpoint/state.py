"""Optimiser and trainer state as flat tensors plus JSON: flattened on save, rebuilt on load,
without pickle."""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from lcrl.checkpoint.files import CheckpointError

# numpy dtypes stored as tensors of the same dtype; every other dtype is stored as raw bytes.
_NATIVE_NUMPY_DTYPES = frozenset(
    np.dtype(t)
    for t in (
        np.bool_,
        np.uint8,
        np.int8,
        np.int16,
        np.int32,
        np.int64,
        np.float16,
        np.float32,
        np.float64,
    )
)


def flatten_state(state: Any, prefix: str = "") -> tuple[dict[str, torch.Tensor], Any]:
    """Split a nested structure into flat named tensors and a JSON-able skeleton.

    Supported values: dicts (including ``OrderedDict``, whose ``_metadata`` attribute, as set
    by ``Module.state_dict()``, is kept) with ``str`` or ``int`` keys, lists, tuples,
    tensors, numpy arrays and scalars, and ``None``/``bool``/``int``/``float``/``str``.
    Integers of any size are kept exactly (JSON integers are unbounded in Python); non-finite
    floats are encoded explicitly.

    Every tensor and numpy array is replaced in the skeleton by a node naming its entry in
    the returned tensor dict, so :func:`unflatten_state` can rebuild the structure with int
    keys as int, tuples as tuples, and numpy arrays as numpy arrays of the same dtype and
    shape. Tensors are neither copied nor moved; the same tensor object appearing twice is
    stored once and comes back as one object. Numpy arrays of the common numeric and bool
    dtypes become tensors of that dtype (sharing memory where possible); other dtypes
    (unsigned 16/32/64-bit, complex, strings, datetimes, non-native byte order) become
    ``uint8`` tensors of their raw bytes.

    Args:
        state: The structure to split.
        prefix: Prepended, followed by ``"."``, to every tensor name (e.g. the state's name),
            so that several flattened states can share one tensor file.

    Returns:
        ``(tensors, skeleton)``: tensor names to tensors, and a structure made only of JSON
        types (dicts with str keys, lists, str, int, float, bool, None).

    Raises:
        CheckpointError: If the structure holds an unsupported value (object arrays,
            structured dtypes, sparse tensors, sets, arbitrary objects, keys other than
            str/int); the message gives the value's location.
    """
    flattener = _Flattener(prefix)
    skeleton = flattener.encode(state, [])
    return flattener.tensors, skeleton


def unflatten_state(tensors: Mapping[str, torch.Tensor], skeleton: Any) -> Any:
    """Rebuild the structure that :func:`flatten_state` split.

    Args:
        tensors: Tensor names to tensors (at least every name the skeleton refers to).
        skeleton: The skeleton returned by :func:`flatten_state` (possibly after a JSON round
            trip).

    Returns:
        The rebuilt structure. Tensors are the objects from ``tensors`` (not copied); numpy
        arrays stored natively are views of them (moved to CPU first if needed).

    Raises:
        CheckpointError: If the skeleton is malformed or names a tensor that is missing or
            has the wrong dtype or size.
    """
    return _decode(skeleton, tensors, "<root>")


class _Flattener:
    """Walks a structure, collecting tensors and producing the skeleton."""

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.tensors: dict[str, torch.Tensor] = {}
        self._names_by_id: dict[int, str] = {}

    def _name(self, path: list[str]) -> str:
        base = ".".join([self.prefix, *path]) if self.prefix else ".".join(path)
        base = base or "value"
        name, n = base, 1
        while name in self.tensors:
            n += 1
            name = f"{base}#{n}"
        return name

    def encode(self, obj: Any, path: list[str]) -> Any:
        if obj is None or isinstance(obj, (bool, int, str)):
            return obj
        if isinstance(obj, float):
            if math.isfinite(obj):
                return obj
            return {"type": "float", "value": repr(obj)}  # 'nan', 'inf' or '-inf'
        if isinstance(obj, torch.Tensor):
            return self._tensor(obj, path)
        if isinstance(obj, np.ndarray):
            return self._ndarray(obj, path, "ndarray")
        if isinstance(obj, np.generic):
            return self._ndarray(np.asarray(obj), path, "npscalar")
        if isinstance(obj, Mapping):
            return self._mapping(obj, path)
        if isinstance(obj, (list, tuple)):
            items = [self.encode(v, [*path, str(i)]) for i, v in enumerate(obj)]
            return {"type": "tuple" if isinstance(obj, tuple) else "list", "items": items}
        raise CheckpointError(
            f"cannot store state at '{_where(path)}': expected a tensor, numpy array, "
            f"dict, list, tuple, str, int, float, bool or None but found {type(obj).__name__}"
        )

    def _mapping(self, obj: Mapping[Any, Any], path: list[str]) -> dict[str, Any]:
        items = []
        for key, value in obj.items():
            if not isinstance(key, (str, int)):
                raise CheckpointError(
                    f"cannot store state at '{_where(path)}': expected str or int dict keys "
                    f"but found key {key!r} of type {type(key).__name__}"
                )
            items.append([key, self.encode(value, [*path, str(key)])])
        node: dict[str, Any] = {"type": "dict", "items": items}
        if isinstance(obj, OrderedDict):
            node["ordered"] = True
            metadata = getattr(obj, "_metadata", None)
            if isinstance(metadata, Mapping):
                node["metadata"] = self.encode(metadata, [*path, "_metadata"])
        return node

    def _tensor(self, t: torch.Tensor, path: list[str]) -> dict[str, Any]:
        if t.layout != torch.strided:
            raise CheckpointError(
                f"cannot store state at '{_where(path)}': expected a dense (strided) tensor "
                f"but found layout {t.layout}"
            )
        name = self._names_by_id.get(id(t))
        if name is None:
            name = self._name(path)
            self.tensors[name] = t
            self._names_by_id[id(t)] = name
        return {"type": "tensor", "name": name}

    def _ndarray(self, a: np.ndarray, path: list[str], kind: str) -> dict[str, Any]:
        dtype = a.dtype
        if dtype.hasobject or dtype.names is not None:
            what = "object" if dtype.hasobject else "structured"
            raise CheckpointError(
                f"cannot store state at '{_where(path)}': expected a numpy array of a plain "
                f"dtype but found {what} dtype {dtype}"
            )
        name = self._name(path)
        # (np.ascontiguousarray would turn a 0-d array into a 1-d one.)
        if not a.flags.c_contiguous or not a.flags.writeable:
            a = a.copy(order="C")
        if dtype in _NATIVE_NUMPY_DTYPES and dtype.isnative:
            self.tensors[name] = torch.from_numpy(a)
            encoding = "native"
        else:
            self.tensors[name] = torch.from_numpy(a.reshape(-1).view(np.uint8))
            encoding = "bytes"
        return {
            "type": kind,
            "name": name,
            "dtype": dtype.str,
            "shape": list(a.shape),
            "encoding": encoding,
        }


def _where(path: list[str]) -> str:
    return ".".join(path) if path else "<root>"


def _decode(node: Any, tensors: Mapping[str, torch.Tensor], where: str) -> Any:
    if node is None or isinstance(node, (bool, int, float, str)):
        return node
    if not isinstance(node, dict) or "type" not in node:
        raise CheckpointError(
            f"malformed state skeleton at '{where}': expected a value or a typed node "
            f"but found {type(node).__name__}"
        )
    kind = node["type"]
    try:
        if kind == "dict":
            out: Any = OrderedDict() if node.get("ordered") else {}
            for key, value in node["items"]:
                out[key] = _decode(value, tensors, f"{where}.{key}")
            if "metadata" in node:
                out._metadata = _decode(node["metadata"], tensors, f"{where}._metadata")
            return out
        if kind in ("list", "tuple"):
            items = [_decode(v, tensors, f"{where}.{i}") for i, v in enumerate(node["items"])]
            return tuple(items) if kind == "tuple" else items
        if kind == "float":
            return float(node["value"])
        if kind == "tensor":
            return _lookup(tensors, node["name"], where)
        if kind in ("ndarray", "npscalar"):
            array = _decode_ndarray(node, tensors, where)
            return array[()] if kind == "npscalar" else array
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, CheckpointError):
            raise
        raise CheckpointError(
            f"malformed state skeleton at '{where}': bad {kind!r} node ({exc!r})"
        ) from exc
    raise CheckpointError(
        f"malformed state skeleton at '{where}': expected a node type among dict, list, "
        f"tuple, float, tensor, ndarray, npscalar but found {kind!r}"
    )


def _lookup(tensors: Mapping[str, torch.Tensor], name: str, where: str) -> torch.Tensor:
    try:
        return tensors[name]
    except KeyError:
        raise CheckpointError(
            f"state at '{where}' expected tensor '{name}' but no tensor of that name was found"
        ) from None


def _decode_ndarray(
    node: dict[str, Any], tensors: Mapping[str, torch.Tensor], where: str
) -> np.ndarray:
    t = _lookup(tensors, node["name"], where).detach().cpu()
    dtype = np.dtype(node["dtype"])
    shape = tuple(int(n) for n in node["shape"])
    if node["encoding"] == "native":
        array = t.numpy()
        if array.dtype != dtype or array.shape != shape:
            raise CheckpointError(
                f"state at '{where}': expected array '{node['name']}' of dtype {dtype} and "
                f"shape {shape} but found dtype {array.dtype} and shape {array.shape}"
            )
        return array
    raw = t.numpy()
    expected = dtype.itemsize * math.prod(shape)
    if raw.dtype != np.uint8 or raw.size != expected:
        raise CheckpointError(
            f"state at '{where}': expected {expected} raw bytes for array '{node['name']}' "
            f"but found {raw.size} elements of dtype {raw.dtype}"
        )
    return np.frombuffer(bytearray(raw.tobytes()), dtype=dtype).reshape(shape)
