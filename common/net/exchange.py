"""The pipeline's objects on the wire: frames, maps and poses between tracker and mapper.

The one place that turns `FrameState`s into `MappingBatch`es and back, and a map with its
poses into a `MapSnapshot` and back, so both service processes convert the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
import torch

from dimslam.common.geometry.camera import Camera
from dimslam.common.net.messages import MappingBatch, MappingFrame, MapSnapshot, MessageError
from dimslam.common.optim.window import FrameState, image_tensor


def pose_array(T_wc: torch.Tensor) -> np.ndarray:
    """A pose as it travels: `(4, 4)` float64 on the CPU."""
    return T_wc.detach().cpu().double().numpy()


def pose_tensor(T_wc: np.ndarray, device: torch.device) -> torch.Tensor:
    """A received pose as the pipeline holds it: `(4, 4)` float32 on `device`."""
    return torch.from_numpy(T_wc).float().to(device)


def to_batch(
    frames: Iterable[FrameState],
    round_: int,
    camera: Camera,
    keyframes: bool = False,
    live: bool = False,
) -> MappingBatch:
    """The frames that still hold an image as a mapping batch (`keyframes`: all flagged;
    `live`: from a live camera)."""
    items = tuple(
        MappingFrame(
            f.index,
            f.timestamp,
            (f.rgb * 255.0).round().byte().cpu().numpy(),
            pose_array(f.T_wc),
            keyframes or f.keyframe,
        )
        for f in frames
        if f.rgb is not None
    )
    return MappingBatch(round_, items, camera, live)


def from_batch(batch: MappingBatch, device: torch.device) -> list[FrameState]:
    """A mapping batch's frames as the pipeline holds them."""
    return [
        FrameState(
            f.seq,
            f.timestamp,
            image_tensor(f.rgb, device),
            pose_tensor(f.T_wc, device),
            f.keyframe,
        )
        for f in batch.frames
    ]


def to_snapshot(
    version: int,
    round_: int,
    digest: str,
    field: torch.nn.Module,
    posed: Iterable[FrameState],
    keyframes: Iterable[FrameState],
    pose: Callable[[FrameState], torch.Tensor] = lambda f: f.T_wc,
) -> MapSnapshot:
    """The map's tensors, the poses of `posed` (`pose`: the current ones by default) and the
    keyframe numbers."""
    return MapSnapshot(
        version,
        round_,
        digest,
        {k: v.detach().cpu().numpy() for k, v in field.state_dict().items()},
        {f.index: pose_array(pose(f)) for f in posed},
        tuple(f.index for f in keyframes),
    )


def load_map(field: torch.nn.Module, snap: MapSnapshot) -> None:
    """Swap a snapshot's tensors into `field`.

    Raises:
        MessageError: the tensors do not fit the field (names, shapes, block coordinates).
    """
    try:
        field.load_state_dict({k: torch.from_numpy(v) for k, v in snap.state.items()})
    except (RuntimeError, ValueError) as e:
        raise MessageError(f"snapshot {snap.version} does not fit this map: {e}") from e


def snapshot_poses(snap: MapSnapshot, device: torch.device) -> dict[int, torch.Tensor]:
    """A snapshot's refined poses by frame number, as the pipeline holds them."""
    return {i: pose_tensor(T, device) for i, T in snap.poses.items()}
