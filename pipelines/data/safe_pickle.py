"""Reading a released ``.pkl`` of plain data without running the code a pickle can name.

``pickle.load`` calls whatever ``module.name`` a file asks for, so a QA file from the internet must not go through it.
``load_plain`` allows only data: containers and scalars (which need no global at all), ``OrderedDict``, and numpy's
array and scalar reconstruction (what ``torch.load(weights_only=True)`` also allows); any other global is refused,
naming the file and the global, before anything is called. Written here because the standard library has no
restricted loader; ``Unpickler.find_class`` is its documented hook for exactly this.
"""

from __future__ import annotations

import collections
import pickle
from pathlib import Path
from typing import Any

from pipelines.data.layout import DataError

_NUMPY = {
    ("numpy", "dtype"),
    ("numpy", "ndarray"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
}
_ALLOWED = {("collections", "OrderedDict"): collections.OrderedDict}


class _PlainUnpickler(pickle.Unpickler):
    def __init__(self, file, where: str):
        super().__init__(file)
        self.where = where

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _ALLOWED:
            return _ALLOWED[module, name]
        if (module, name) in _NUMPY:
            import numpy  # noqa: F401  (the allowed numpy globals resolve through the normal lookup)

            return super().find_class(module, name)
        raise DataError(
            f"{self.where}: the pickle names {module}.{name}, which is not plain data (lists, dicts, strings, numbers, "
            "numpy arrays); refusing to load it"
        )


def load_plain(path: Path, where: str) -> Any:
    """The object in the pickle file ``path`` if it holds plain data only; a DataError naming ``where`` otherwise."""
    try:
        with open(path, "rb") as f:
            return _PlainUnpickler(f, where).load()
    except DataError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError) as e:
        raise DataError(f"{where}: not a readable pickle ({type(e).__name__}: {e})") from e
