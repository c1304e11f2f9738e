"""Reading pickles that may come from anywhere (the references' published episode files) without
running their code.

The references' pickles hold a ``datasets.offline_controller_with_small_rotation.ThorAgentState``
start state, numpy arrays and torch tensors. :func:`load_untrusted` resolves only a fixed set of
harmless globals (containers, plain numeric numpy arrays, torch tensors rebuilt with
``weights_only`` loading); every other global becomes an inert :class:`Placeholder` that records
its constructor arguments and state. Before the unpickler runs, the opcodes are walked so that a
damaged file cannot make it allocate what it claims.
"""

from __future__ import annotations

import collections
import copyreg
import io
import pickle
import re
from collections.abc import Callable
from typing import Any

import numpy as np


def load_untrusted(data: bytes) -> Any:
    """The object a pickle holds, with every global outside the allow-list a :class:`Placeholder`
    and every array rebuilt from plain numeric states. Raises whatever a crafted file makes the
    allowed constructors raise (callers turn it into their format error)."""
    check_opcodes(data)
    return _materialize(_RestrictedUnpickler(io.BytesIO(data)).load())


class Placeholder:
    """Stand-in for a class that is not importable here (``ThorAgentState``...)."""

    pickled_module = ""
    pickled_name = ""

    def __init__(self, *args: Any, **kwargs: Any):
        self.args = args
        self.__dict__.update(kwargs)

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict, slots) of __slots__ classes
            for part in state:
                if isinstance(part, dict):
                    self.__dict__.update(part)
        elif isinstance(state, dict):
            self.__dict__.update(state)
        else:
            self.state = state

    def __call__(self, *args: Any, **kwargs: Any) -> Placeholder:
        # A REDUCE through a placeholder "function" (getattr(obj, name)(...)) stays inert too.
        return Placeholder(*args, **kwargs)

    def __repr__(self) -> str:
        # Names only: the values come from the file and may be shared or nested without bound.
        fields = [k if isinstance(k, str) else type(k).__name__ for k in self.__dict__ if k != "args"]
        return f"<{self.pickled_module}.{self.pickled_name} with {', '.join(fields[:8]) or 'no fields'}>"


def _safe_load_from_bytes(data: bytes) -> Any:
    import torch

    return torch.load(io.BytesIO(data), weights_only=True)


#: dtype names a pickled array may have: booleans and plain numbers of the usual widths.
_NUMERIC_DTYPE = re.compile(r"[biufc]\d{1,2}")


class _PickledDtype:
    """``numpy.dtype(name, align, copy)`` of a pickle, checked when its state arrives: only plain
    numeric types (kinds b, i, u, f, c; no fields, no sub-arrays) become a dtype."""

    def __init__(self, name: Any = "", align: Any = False, copy: Any = False):
        self.name = name
        self.dtype: np.dtype | None = None

    def __setstate__(self, state: Any) -> None:
        order = state[1] if isinstance(state, tuple) and len(state) > 1 else "|"
        subarray = state[2] if isinstance(state, tuple) and len(state) > 2 else None
        fields = state[3:5] if isinstance(state, tuple) and len(state) > 4 else (None, None)
        if not (isinstance(self.name, str) and _NUMERIC_DTYPE.fullmatch(self.name)):
            raise pickle.UnpicklingError(f"array dtype {self.name!r} is not a plain numeric type")
        if subarray is not None or any(f is not None for f in fields) or order not in ("<", ">", "|", "="):
            raise pickle.UnpicklingError(
                f"array dtype {self.name!r} has fields, sub-arrays or a bad byte order"
            )
        self.dtype = np.dtype(self.name).newbyteorder(order if order != "|" else "=")

    def resolve(self) -> np.dtype:
        if self.dtype is None:
            self.__setstate__(())
        return self.dtype


def _dtype_of(value: Any) -> np.dtype:
    if not isinstance(value, _PickledDtype):
        raise pickle.UnpicklingError(f"array dtype given as {type(value).__name__}")
    return value.resolve()


class _PickledArray:
    """A numpy array of a pickle (``_reconstruct`` then its state), rebuilt by :meth:`array` from a
    checked shape, dtype and the exact number of bytes; anything else is an UnpicklingError."""

    def __init__(self, *args: Any):
        self.state: Any = None

    def __setstate__(self, state: Any) -> None:
        self.state = state

    def array(self) -> np.ndarray:
        state = self.state
        if not (isinstance(state, tuple) and len(state) == 5):
            raise pickle.UnpicklingError("array state is not (version, shape, dtype, fortran, data)")
        _, shape, dtype, fortran, data = state
        dtype = _dtype_of(dtype)
        if not (isinstance(shape, tuple) and all(isinstance(n, int) and 0 <= n < 2**31 for n in shape)):
            raise pickle.UnpicklingError(f"array shape {shape!r} is not a tuple of sizes")
        if not isinstance(data, bytes | bytearray):
            raise pickle.UnpicklingError("array data is not raw bytes (object arrays are refused)")
        count = int(np.prod(shape, dtype=np.int64))
        if len(data) != count * dtype.itemsize:
            raise pickle.UnpicklingError(f"array of shape {shape} and dtype {dtype} with {len(data)} bytes")
        flat = np.frombuffer(bytes(data), dtype=dtype, count=count)
        return flat.reshape(shape, order="F" if fortran else "C").copy()


def _pickled_scalar(dtype: Any, data: Any = b"") -> Any:
    dtype = _dtype_of(dtype)
    if not isinstance(data, bytes) or len(data) != dtype.itemsize:
        raise pickle.UnpicklingError(f"numpy scalar of dtype {dtype} with {len(data)} bytes")
    return np.frombuffer(data, dtype=dtype, count=1)[0]


def _materialize(value: Any, depth: int = 0, done: dict[int, Any] | None = None) -> Any:
    """The unpickled structure with every :class:`_PickledArray` rebuilt as an ndarray.

    Each object is visited once (``done``, by id): a pickle can share one list between many
    parents, level after level, and a walk that revisited shared objects would take 2**depth steps.
    A cycle is refused by the depth limit."""
    done = {} if done is None else done
    if depth > 50:
        raise pickle.UnpicklingError("episode data nested deeper than 50 levels (or a cycle)")
    if id(value) in done:
        return done[id(value)]
    result = value
    if isinstance(value, _PickledArray):
        result = value.array()
    elif isinstance(value, _PickledDtype):
        result = value.resolve()
    elif isinstance(value, list):
        result = [_materialize(v, depth + 1, done) for v in value]
    elif isinstance(value, tuple):
        result = tuple(_materialize(v, depth + 1, done) for v in value)
    elif isinstance(value, dict):
        result = {k: _materialize(v, depth + 1, done) for k, v in value.items()}
    elif isinstance(value, Placeholder):
        value.__dict__.update({k: _materialize(v, depth + 1, done) for k, v in value.__dict__.items()})
    done[id(value)] = result
    return result


def _no_size(kind: type) -> Callable[..., Any]:
    """``bytes``/``bytearray`` for a pickle: built from data in the file, never from a size (a
    ``bytes(10**10)`` in a few bytes of pickle would allocate gigabytes)."""

    def build(*args: Any) -> Any:
        if args and isinstance(args[0], int):
            raise pickle.UnpicklingError(f"{kind.__name__} of a size ({args[0]}) in an episode file")
        return kind(*args)

    return build


def _reconstructor(cls: Any, base: Any, state: Any) -> Any:
    """``copyreg._reconstructor`` of protocol 0/1 pickles, for placeholder classes on ``object``
    or a plain container only: other classes and bases (``bytes`` of a size) are refused."""
    if not (isinstance(cls, type) and issubclass(cls, base) and base in _RECONSTRUCTOR_BASES):
        raise pickle.UnpicklingError(f"copyreg._reconstructor of {cls!r} on {base!r}")
    return copyreg._reconstructor(cls, base, state)


_RECONSTRUCTOR_BASES = (object, list, dict, tuple, set, frozenset, int, float, str)


def check_opcodes(data: bytes) -> None:
    """Walk the pickle's opcodes before the C unpickler runs: a length that runs past the end of the
    data, or a memo index beyond the objects stored so far, is refused here, because the unpickler
    would first allocate what it claims (gigabytes from a few bytes of a damaged file)."""
    import pickletools

    stored = 0
    try:
        for opcode, arg, _ in pickletools.genops(data):
            if opcode.name == "MEMOIZE":
                stored += 1
            elif opcode.name in ("PUT", "BINPUT", "LONG_BINPUT"):
                if not (isinstance(arg, int) and 0 <= arg <= stored):
                    raise pickle.UnpicklingError(f"memo index {arg!r} out of order")
                stored = max(stored, arg + 1)
            elif opcode.name in ("GET", "BINGET", "LONG_BINGET") and not (
                isinstance(arg, int) and 0 <= arg < stored
            ):
                raise pickle.UnpicklingError(f"memo index {arg!r} was never stored")
    except ValueError as error:  # pickletools' own complaints (truncated data, bad opcodes, ...)
        raise pickle.UnpicklingError(str(error)) from None


def _safe_globals() -> dict[tuple[str, str], Any]:
    import builtins

    allowed: dict[tuple[str, str], Any] = {}
    for name in (
        "list",
        "dict",
        "set",
        "frozenset",
        "tuple",
        "int",
        "float",
        "complex",
        "str",
        "bool",
        "slice",
        "object",
    ):
        # "__builtin__" is how Python 2 pickles (protocol <= 2) name the same module.
        allowed[("builtins", name)] = allowed[("__builtin__", name)] = getattr(builtins, name)
    for name in ("bytes", "bytearray"):
        allowed[("builtins", name)] = allowed[("__builtin__", name)] = _no_size(getattr(builtins, name))
    # range is left out: list(range(10**12)) would be a few bytes of pickle.
    allowed[("copyreg", "_reconstructor")] = _reconstructor
    allowed[("copy_reg", "_reconstructor")] = _reconstructor
    allowed[("_codecs", "encode")] = __import__("codecs").encode
    allowed[("collections", "OrderedDict")] = collections.OrderedDict
    # numpy's own reconstructors would trust the file's dtype and byte states (a crafted structured
    # dtype can smuggle a pointer into an "object" field): arrays are rebuilt here from plain numeric
    # states only (:class:`_PickledArray`), after the whole file is read.
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed[(module, "_reconstruct")] = _PickledArray
        allowed[(module, "scalar")] = _pickled_scalar
    allowed[("numpy", "dtype")] = _PickledDtype
    allowed[("numpy", "ndarray")] = _PickledArray
    try:
        import torch._utils
    except ImportError:  # without torch, tensors stay placeholders
        return allowed
    allowed[("torch._utils", "_rebuild_tensor_v2")] = torch._utils._rebuild_tensor_v2
    allowed[("torch._utils", "_rebuild_tensor")] = torch._utils._rebuild_tensor
    allowed[("torch.storage", "_load_from_bytes")] = _safe_load_from_bytes
    return allowed


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that maps every global outside a harmless allow-list to a :class:`Placeholder`."""

    _allowed: dict[tuple[str, str], Any] | None = None

    def __init__(self, file: Any):
        super().__init__(file)
        if _RestrictedUnpickler._allowed is None:
            _RestrictedUnpickler._allowed = _safe_globals()
        self._placeholders: dict[tuple[str, str], type] = {}

    def find_class(self, module: str, name: str) -> Any:
        found = self._allowed.get((module, name))
        if found is not None:
            return found
        key = (module, name)
        if key not in self._placeholders:
            self._placeholders[key] = type(
                name, (Placeholder,), {"pickled_module": module, "pickled_name": name}
            )
        return self._placeholders[key]
