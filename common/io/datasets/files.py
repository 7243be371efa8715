"""The text files the layouts share: index and pose tables, timestamp association, poses
from quaternion or matrix rows. Every parser names the file and line of a malformed row."""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from dimslam.common.errors import DatasetError
from dimslam.common.geometry import pose
from dimslam.common.io.datasets.base import Entry

# Largest gap (seconds) between a frame and the ground-truth sample it is paired with (the
# TUM benchmark's own association tolerance).
MAX_GT_DT = 0.02


def natural_key(name: str) -> tuple:
    """Sort key putting `frame2` before `frame10`."""
    return tuple(int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name))


def read_rows(path: Path, what: str, sep: str | None = None) -> list[tuple[int, list[str]]]:
    """The non-comment lines of a text index file, split into fields.

    Args:
        path: the file.
        what: what the file is, for the message if it cannot be read.
        sep: field separator; None splits on whitespace (and commas).

    Returns:
        `(line_number, fields)` for every line with content (`#` starts a comment).

    Raises:
        DatasetError: naming the file if it cannot be read.
    """
    try:
        text = path.read_text()
    except OSError as e:
        raise DatasetError(f"{path}: cannot read {what} ({e.strerror})") from None
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: {what} is not a text file") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.split("#")[0].strip()
        if not line:
            continue
        fields = line.split(sep) if sep else line.replace(",", " ").split()
        rows.append((number, [f.strip() for f in fields]))
    return rows


def numeric_table(
    path: Path, rows: Sequence[tuple[int, list[str]]], columns: int, form: str
) -> np.ndarray:
    """The first `columns` fields of `rows` as a finite float64 `(N, columns)` array.

    Args:
        path: the file the rows come from, for messages.
        rows: from `read_rows`.
        columns: how many leading fields to use; shorter lines are an error.
        form: the expected line, for messages, e.g. `'timestamp tx ty tz qx qy qz qw'`.

    Raises:
        DatasetError: naming `path:line` of the first short, non-numeric or non-finite line.
    """
    for number, fields in rows:
        if len(fields) < columns:
            raise DatasetError(
                f"{path}:{number}: expected {columns} values '{form}', got {len(fields)}"
            )
    try:
        # Fast path: numpy parses the whole table at once (EuRoC ground truth: ~40k lines).
        table = np.array([fields[:columns] for _, fields in rows], dtype=np.float64)
    except ValueError:
        table = np.array([_floats(path, number, fields[:columns]) for number, fields in rows])
    table = table.reshape(len(rows), columns)
    bad = ~np.isfinite(table).all(axis=1)
    if bad.any():
        number, fields = rows[int(np.argmax(bad))]
        raise DatasetError(f"{path}:{number}: non-finite value in {' '.join(fields)!r}")
    return table


def read_table(path: Path, columns: int, form: str, sep: str | None = None) -> np.ndarray:
    """A numeric text file (`#` comments) as a finite float64 `(N, columns)` array.

    Args:
        path: the file.
        columns: how many leading fields of each line to use; shorter lines are an error.
        form: the expected line, for messages.
        sep: field separator; None for whitespace.

    Raises:
        DatasetError: naming the file if it cannot be read, or `path:line` of the first bad line.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numpy warns about an empty file; an error follows
            table = np.loadtxt(path, comments="#", delimiter=sep, usecols=range(columns), ndmin=2)
        if np.isfinite(table).all():
            return table
    except OSError as e:
        raise DatasetError(f"{path}: cannot read {form} ({e.strerror})") from None
    except ValueError:
        pass  # the slow path below finds the line to name
    return numeric_table(path, read_rows(path, form, sep), columns, form)


def line_of(path: Path, row: int) -> int:
    """The line number of the `row`-th data line of `path`, for messages."""
    return read_rows(path, "text")[row][0]


def _floats(path: Path, number: int, fields: list[str]) -> list[float]:
    try:
        return [float(f) for f in fields]
    except ValueError:
        line = " ".join(fields)
        raise DatasetError(f"{path}:{number}: not a number in {line!r}") from None


def associate(times: np.ndarray, gt_times: np.ndarray, max_dt: float = MAX_GT_DT) -> np.ndarray:
    """For each of `times` `(N,)`, the index of the nearest of `gt_times` `(M,)` within
    `max_dt` seconds, or -1 where there is none."""
    if len(gt_times) == 0:
        return np.full(len(times), -1)
    order = np.argsort(gt_times, kind="stable")
    sorted_t = gt_times[order]
    right = np.searchsorted(sorted_t, times).clip(0, len(sorted_t) - 1)
    left = (right - 1).clip(0, len(sorted_t) - 1)
    nearest = np.where(
        np.abs(sorted_t[left] - times) <= np.abs(sorted_t[right] - times), left, right
    )
    ok = np.abs(sorted_t[nearest] - times) <= max_dt
    return np.where(ok, order[nearest], -1)


def attach(entries: Iterable[Entry], poses: np.ndarray, matches: np.ndarray) -> list[Entry]:
    """`entries` with `poses[matches[i]]` attached, none where `matches[i] < 0`."""
    return [
        Entry(e.timestamp, e.path, poses[m].copy() if m >= 0 else None)
        for e, m in zip(entries, matches, strict=True)
    ]


def quat_poses(t: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """`(N, 4, 4)` float64 poses from translations `(N, 3)` and quaternions `(N, 4)` xyzw."""
    q = torch.from_numpy(np.ascontiguousarray(q_xyzw, dtype=np.float64))
    R = pose.quat_to_matrix(q)
    return pose.make_pose(R, torch.from_numpy(np.ascontiguousarray(t, dtype=np.float64))).numpy()


def matrix_poses(path: Path, table: np.ndarray) -> np.ndarray:
    """`(N, 4, 4)` poses from the `(N, 16)` row-major table read from `path`.

    Raises:
        DatasetError: naming `path:line` of a pose whose last row is not `0 0 0 1`.
    """
    poses = table.reshape(-1, 4, 4)
    bad = ~np.all(np.abs(poses[:, 3] - [0, 0, 0, 1]) < 1e-6, axis=1)
    if bad.any():
        number = line_of(path, int(np.argmax(bad)))
        raise DatasetError(f"{path}:{number}: not a rigid transform (last row must be 0 0 0 1)")
    return poses
