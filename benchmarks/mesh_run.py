"""Mesh the final map of a service run and evaluate it against the dataset's mesh.

    python benchmarks/mesh_run.py OUT DATASET [--set mapper.mesh_voxel=0.05 ...]

OUT is the folder of a `dimslam run` through the service: its `config.json` (the settings),
`map.msgpack` (the mapper's last snapshot), `trajectory.txt` and `keyframes.txt` (the final
poses; the keyframes' images are read again from DATASET for their plane sweeps). The mesh is
extracted exactly as the mapper does at the end of a run (`Mapper.extract_mesh`), written to
OUT/mesh.ply and evaluated with the project's evaluator (the trajectory's Sim(3) applied).
Useful for runs made with --no-mesh, or to compare mesh settings on one map.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import dimslam.common  # noqa: F401  (OMP_WAIT_POLICY must be set before torch loads OpenMP)

# isort: split
import torch

from dimslam.common.config import PRESETS
from dimslam.common.eval.report import evaluate_files, format_metrics
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.io.trajectory import Trajectory, read_tum
from dimslam.common.map.mesh import write_mesh
from dimslam.common.net.exchange import load_map
from dimslam.common.net.messages import MapSnapshot
from dimslam.common.optim.window import FrameState, image_tensor
from dimslam.common.options import flat_settings, overrides_or_exit, setting
from dimslam.mapper.mapper import Mapper


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path)
    p.add_argument("dataset")
    p.add_argument(
        "--set", nargs="*", action="extend", type=setting, default=[], metavar="SECTION.FIELD=V"
    )
    args = p.parse_args()
    recorded = json.loads((args.out / "config.json").read_text())
    settings = flat_settings({k: v for k, v in recorded.items() if k in ("map", "render", "loss",
                              "tracker", "mapper", "width", "seed")})  # fmt: skip
    settings.update(dict(args.set))
    cfg = overrides_or_exit(p, PRESETS["paper"], settings)
    reader = open_dataset(args.dataset, options=ReaderOptions(width=cfg.width or None))
    snap = MapSnapshot.from_bytes((args.out / "map.msgpack").read_bytes())
    mapper = Mapper(
        cfg.mapper, cfg.map, cfg.loss, cfg.render, cfg.tracker.overlap,
        cfg.tracker.overlap_pixels, reader.camera, torch.device("cpu"), torch.Generator(),
    )  # fmt: skip
    load_map(mapper.field, snap)
    trajectory = read_tum(args.out / "trajectory.txt")
    poses = torch.from_numpy(trajectory.poses).float()
    keyframes = _keyframes(read_tum(args.out / "keyframes.txt"), trajectory, reader)
    started = time.perf_counter()
    mesh = mapper.extract_mesh(poses, cfg.render.far, keyframes)
    print(f"mesh: {len(mesh.faces)} faces in {time.perf_counter() - started:.1f} s")
    write_mesh(mesh, args.out / "mesh.ply")
    metrics = evaluate_files(args.out / "trajectory.txt", args.dataset, mesh=args.out / "mesh.ply")
    print(format_metrics(metrics))


def _keyframes(keyframes: Trajectory, trajectory: Trajectory, reader) -> list[FrameState]:
    """The run's keyframes at their final poses with their images from `reader`, each indexed
    by its position in `trajectory` (timestamps matched to a microsecond)."""
    wanted = {
        round(float(t), 6): T for t, T in zip(keyframes.timestamps, keyframes.poses, strict=True)
    }
    index = {round(float(t), 6): i for i, t in enumerate(trajectory.timestamps)}
    found = []
    for frame in reader:
        stamp = round(frame.timestamp, 6)
        if stamp in wanted and stamp in index:
            T = torch.from_numpy(wanted[stamp]).float()
            found.append(
                FrameState(index[stamp], frame.timestamp, image_tensor(frame.rgb), T, True)
            )
    if len(found) < len(wanted):
        raise SystemExit(f"error: {len(wanted) - len(found)} keyframes not found in the dataset")
    return found


if __name__ == "__main__":
    main()
