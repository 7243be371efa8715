"""The one shape-check helper: every public function validates its inputs through it."""

from __future__ import annotations

from typing import Any


def check_shape(name: str, x: Any, shape: tuple) -> None:
    """Raise ValueError unless `x.shape` matches `shape`.

    Args:
        name: the argument's name, for the message.
        x: a numpy array or torch tensor.
        shape: expected shape; `None` matches any size, a leading `...` matches any number
            of batch dimensions. Example: `(..., 4, 4)`, `(None, 3)`.
    """
    actual = tuple(x.shape)
    if shape and shape[0] is Ellipsis:
        tail = shape[1:]
        ok = len(actual) >= len(tail) and all(
            want is None or want == got
            for want, got in zip(tail, actual[len(actual) - len(tail) :], strict=True)
        )
    else:
        ok = len(actual) == len(shape) and all(
            want is None or want == got for want, got in zip(shape, actual, strict=True)
        )
    if not ok:
        spec = ", ".join("..." if s is Ellipsis else "N" if s is None else str(s) for s in shape)
        raise ValueError(f"{name}: expected shape ({spec}), got {actual}")
