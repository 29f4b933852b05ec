"""The lineage's episode lists ``test_val_split/{room}_{test,val}_22.pkl``: writing them, and reading them safely.

Each file is a pickled Python list of dicts, one per episode (VTNet / DOA / IOM / DAT evaluate on them)::

    {"scene": "FloorPlan24", "state": "0.50|3.50|315|30", "goal_object_type": "Pot",
     "task_data": ["Pot|+00.62|+00.85|+01.40"], "glove_embedding": <float32 array (60, 1), one-hot>}

``state`` is a state key (``x|z|rotation|horizon``); ``task_data`` the object ids of the target type in the
scene (the lineage's evaluator counts success when one of them is in its visibility map at the final state,
its planner finds shortest paths to the states listing them). ``glove_embedding`` is a ``(60, 1)`` one-hot
array; tsnav sets the target's index among the 22 categories (``constants.TARGET_CATEGORIES``). The
lineage's 22-class agents take the target from ``goal_object_type``.

Writing plain dicts, lists, strings and numpy arrays with :mod:`pickle` is safe. *Reading* a pickle runs
whatever callables it names, so :func:`read_split` uses :class:`RestrictedUnpickler`, which admits only
builtin containers and scalars and numpy's array reconstruction: a pickle that names anything else (e.g.
``os.system`` or ``builtins.exec``) stops with one line before any of it runs.

Success radius: the lineage's evaluator counts success by its visibility map (in view within 1.5 m); the
paper's rule (and tsnav's default) is 1.0 m. A list made for one radius can hold starts from which the
other rule already succeeds. The radius a list was made for is written beside the lists in
:data:`INFO_FILE`; :func:`tsnav.sim.lineage.episodes_from_splits` turns lists into tsnav episodes with the
optimal lengths of the radius it is given.
"""

from __future__ import annotations

import builtins
import io
import pickle
from pathlib import Path

import numpy as np

from ..atomic import atomic_write_bytes, atomic_write_json
from ..constants import CATEGORY_INDEX, ROOM_TYPES
from .names import scene_base_name  # re-exported: SAVN's folder names carry the suffix, the lists do not

#: Room-type names of the split files (``{room}_{split}_22.pkl``).
SPLIT_ROOMS = ROOM_TYPES
SPLIT_NAMES = ("test", "val")
#: Shape of the ``glove_embedding`` field.
GLOVE_SHAPE = (60, 1)
#: Written beside the lists: which success radius, dataset and episode counts they were made for.
INFO_FILE = "tsnav_split_info.json"
#: Keys every record must have.
RECORD_KEYS = ("scene", "state", "goal_object_type", "task_data")


def split_file_name(room: str, split: str) -> str:
    """``{room}_{split}_22.pkl``, the lineage's name of a room type's episode list."""
    return f"{room}_{split}_22.pkl"


def target_one_hot(target: str) -> np.ndarray:
    """The ``(60, 1)`` float32 one-hot ``glove_embedding`` of ``target`` (index in the 22 categories)."""
    v = np.zeros(GLOVE_SHAPE, np.float32)
    v[CATEGORY_INDEX[target], 0] = 1.0
    return v


def split_record(scene: str, state: str, target: str, task_data: list[str]) -> dict:
    """One episode in the lineage's format (see the module docstring)."""
    return {
        "scene": str(scene),
        "state": str(state),
        "goal_object_type": str(target),
        "task_data": [str(t) for t in task_data],
        "glove_embedding": target_one_hot(target),
    }


def write_split(path: str | Path, records: list[dict]) -> Path:
    """Pickle ``records`` (plain dicts, lists, strings, numpy arrays) to ``path``, atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, pickle.dumps(list(records), protocol=4))
    return path


# ------------------------------------------------------------------------------------------ reading
#: Builtin callables a data pickle may name (containers and scalars; protocol 0-2 pickles build some of
#: them by calling the type). Python 2's module name ``__builtin__`` is accepted for the same names.
_BUILTINS = frozenset(
    {"dict", "list", "tuple", "set", "frozenset", "str", "bytes", "bytearray", "int", "float", "complex", "bool"}
)
#: numpy's array and scalar reconstruction (numpy 1 names it numpy.core, numpy 2 numpy._core).
_NUMPY = {
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
}
#: The functions themselves, taken from numpy's own pickling (so both numpy 1 and 2 names resolve).
_NUMPY_FUNCTIONS = {
    "ndarray": np.ndarray,
    "dtype": np.dtype,
    "_reconstruct": np.zeros(1).__reduce__()[0],
    "scalar": np.float64(0).__reduce__()[0],
    "_frombuffer": np.zeros(1).__reduce_ex__(5)[0],
}


class UnsafePickle(pickle.UnpicklingError):
    """A pickle names a callable outside builtins' containers / scalars and numpy arrays."""


class RestrictedUnpickler(pickle.Unpickler):
    """An unpickler that admits only builtin containers and scalars and numpy arrays (see the module doc).

    Any other global (``os.system``, ``builtins.exec``, ``builtins.open``, ``subprocess.Popen`` ...) raises
    :class:`UnsafePickle` when the unpickler meets it, before it can be called. Persistent ids are refused.
    """

    def find_class(self, module: str, name: str):
        if module in ("builtins", "__builtin__") and name in _BUILTINS:
            return getattr(builtins, name)
        if module == "_codecs" and name == "encode":  # bytes in protocol 2 pickles of numpy arrays
            return _latin1_encode
        if (module, name) in _NUMPY:
            return _NUMPY_FUNCTIONS[name]
        raise UnsafePickle(
            f"the pickle calls {module}.{name}; only builtin containers, numbers, strings and numpy arrays are admitted"
        )

    def persistent_load(self, pid):
        raise UnsafePickle("the pickle uses persistent ids; only plain data is admitted")


def _latin1_encode(text: str, encoding: str = "latin1") -> bytes:
    """``_codecs.encode`` restricted to what pickled numpy buffers use (latin-1 text to bytes)."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise UnsafePickle("the pickle calls _codecs.encode with other arguments than numpy's latin-1 buffers")
    return text.encode("latin1")


def safe_load(data: bytes):
    """Unpickle ``data`` with :class:`RestrictedUnpickler` (Python 2 strings read as latin-1)."""
    return RestrictedUnpickler(io.BytesIO(data), encoding="latin1").load()


class SplitFormatError(ValueError):
    """An episode list that cannot be read (one line naming the file)."""


def read_split(path: str | Path) -> list[dict]:
    """The records of a lineage split file, read with :class:`RestrictedUnpickler` and checked.

    :class:`SplitFormatError` with one line naming the file for a missing file, a pickle that names a
    forbidden callable (its payload never runs), a truncated or corrupt pickle, or content that is not a
    list of episode dicts with ``scene``, ``state``, ``goal_object_type`` and ``task_data``.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SplitFormatError(f"{path}: missing file") from None
    except OSError as e:
        raise SplitFormatError(f"{path}: unreadable ({e.strerror or e})") from None
    try:
        obj = safe_load(data)
    except UnsafePickle as e:
        raise SplitFormatError(f"{path}: refused: {e}") from None
    except Exception as e:  # noqa: BLE001 - any corrupt pickle: truncated, bad opcodes, bad numpy state
        raise SplitFormatError(
            f"{path}: not a readable pickle ({type(e).__name__}: {' '.join(str(e).split())})"
        ) from None
    if not isinstance(obj, list):
        raise SplitFormatError(f"{path}: expected a list of episode dicts, got {type(obj).__name__}")
    for i, r in enumerate(obj):
        if not isinstance(r, dict) or any(k not in r for k in RECORD_KEYS):
            raise SplitFormatError(f"{path}: episode {i} is not a dict with {', '.join(RECORD_KEYS)}")
        if (
            not isinstance(r["scene"], str)
            or not isinstance(r["state"], str)
            or not isinstance(r["goal_object_type"], str)
        ):
            raise SplitFormatError(f"{path}: episode {i}: scene, state and goal_object_type must be strings")
        if not isinstance(r["task_data"], (list, tuple)) or not all(isinstance(t, str) for t in r["task_data"]):
            raise SplitFormatError(f"{path}: episode {i}: task_data must be a list of object ids")
    return obj


def split_records(bank, episodes) -> list[dict]:
    """The lineage's records of tsnav ``episodes`` over ``bank``: ``task_data`` lists the scene's object ids of
    the target type that its visibility map lists (the objects the lineage's evaluator and planner look up)."""
    ids_of: dict[tuple[int, int], list[str]] = {}
    out = []
    for e in episodes:
        i = bank.scene_index(e.scene)
        c = CATEGORY_INDEX[e.target]
        if (i, c) not in ids_of:
            sc = bank.scenes[i]
            cols = np.flatnonzero((np.asarray(sc.object_category) == c) & sc.visible.any(axis=0))
            ids_of[(i, c)] = [str(sc.object_ids[j]) for j in cols]
        out.append(split_record(e.scene, e.start, e.target, ids_of[(i, c)]))
    return out


def write_split_info(folder: str | Path, info: dict) -> Path:
    """Write :data:`INFO_FILE` into the split folder (atomic)."""
    path = Path(folder) / INFO_FILE
    atomic_write_json(path, info, sort_keys=False)
    return path


__all__ = [
    "GLOVE_SHAPE",
    "INFO_FILE",
    "RestrictedUnpickler",
    "SPLIT_NAMES",
    "SPLIT_ROOMS",
    "SplitFormatError",
    "UnsafePickle",
    "read_split",
    "safe_load",
    "scene_base_name",
    "split_file_name",
    "split_record",
    "split_records",
    "target_one_hot",
    "write_split",
    "write_split_info",
]
