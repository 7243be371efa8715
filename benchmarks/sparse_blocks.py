"""Where a sparse map's blocks go: stored against what its keyframes' surfaces need.

    python benchmarks/sparse_blocks.py DATASET FRAMES [--set KEY=VALUE ...]

Runs the cpu preset with `map.grids sparse` (and the end-of-run adjustment off) in this
process on the first FRAMES frames of DATASET, printing every 10 frames the blocks stored
per level (geometry grids, then colour grids) and the map's MB. At the end, from every
keyframe's rays (`Mapper.reclaim`'s 40 px, every pixel):

- the finest levels' blocks a band of 0.1 / 0.3 / 0.6 map units before the rendered depth
  needs (rays with opacity > 0.5): what a map kept near its surfaces would store;
- the rays' opacity, the share that stop (transmittance under `render.STOPPED`) and that
  stop seeing (under `render.SEEN`), and how far behind the rendered depth each of the two
  lies (10th / 50th / 90th percentiles, map units).

`--set` changes settings as `dimslam run`'s flags do (e.g. `map.fine_band=0.3`,
`map.reclaim_every=4`).
"""

from __future__ import annotations

import argparse
import time

import torch

from dimslam.common.config import PRESETS
from dimslam.common.io.datasets import ReaderOptions, open_dataset
from dimslam.common.map.render import camera_rays, render_rays, sample_depths
from dimslam.common.map.sparse import SparseGrids
from dimslam.common.options import overrides_or_exit, setting
from dimslam.common.slam import Slam
from dimslam.mapper.mapper import RECLAIM_WIDTH

BANDS = (0.1, 0.3, 0.6)
QUANTILES = torch.tensor([0.1, 0.5, 0.9])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset")
    p.add_argument("frames", type=int, help="how many of the dataset's first frames")
    p.add_argument("--set", type=setting, action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args()
    if args.frames < 1:
        p.error("frames must be at least 1")
    settings = {"map.grids": "sparse", "bundle.enabled": "false", **dict(args.set)}
    cfg = overrides_or_exit(p, PRESETS["cpu"], settings)
    if cfg.map.grids != "sparse":
        p.error("this counts a sparse map's blocks: leave map.grids sparse")
    torch.set_num_threads(1)
    reader = open_dataset(args.dataset, options=ReaderOptions(end=args.frames))
    slam = Slam(cfg, reader.camera, torch.device("cpu"))
    field = slam.back.field
    started = time.perf_counter()
    for n, frame in enumerate(reader, 1):
        slam.add(frame)
        if n % 10 == 0:
            print(f"frame {n}: {blocks(field)} ({time.perf_counter() - started:.0f} s)", flush=True)
    slam.finish()
    print(f"end: {blocks(field)}")
    surfaces(slam)


def blocks(field) -> str:
    levels = len(field.cfg.voxel_sizes)
    geometry = field.geometry.blocks[:, 0].bincount(minlength=levels).tolist()
    color = field.color.blocks[:, 0].bincount(minlength=field.n_color_levels).tolist()
    return f"blocks per level {geometry}, colour {color}, {field.memory_bytes() / 2**20:.1f} MB"


def surfaces(slam: Slam) -> None:
    field, mapper = slam.back.field, slam.back.mapper
    small = slam.camera.resized(min(slam.camera.width, RECLAIM_WIDTH))
    uv = small.pixels()
    fine = tuple(field.cfg.voxel_sizes[-field.n_color_levels :])
    needed = {band: SparseGrids(fine, 1, 0.0) for band in BANDS}
    opacity, depth, stop, reach = [], [], [], []
    with torch.no_grad():
        for kf in slam.keyframes:
            origins, directions = camera_rays(small, uv, kf.T_wc)
            out = render_rays(field, origins, directions, mapper.render_cfg, with_color=False)
            _, seen, stopped = sample_depths(field, origins, directions, mapper.render_cfg)
            opacity.append(out.opacity), depth.append(out.depth)
            reach.append(seen), stop.append(stopped)
            ok = out.opacity > 0.5
            for band, grids in needed.items():
                t = out.depth[ok, None] + torch.linspace(-band, 0.05, 8)[None]
                grids.allocate(
                    (origins[ok, None] + t[..., None] * directions[ok, None]).view(-1, 3)
                )
    for band, grids in needed.items():
        counts = grids.blocks[:, 0].bincount(minlength=len(fine)).tolist()
        print(f"the keyframes' surfaces, band {band}: fine blocks {counts}")
    opacity, depth = torch.cat(opacity), torch.cat(depth)
    far = mapper.render_cfg.far
    print(
        f"{opacity.numel()} rays of {len(slam.keyframes)} keyframes: opacity > 0.5 "
        f"{100 * (opacity > 0.5).float().mean():.1f} %, median depth {depth.median():.2f}"
    )
    for name, at in (("stop", torch.cat(stop)), ("stop seeing", torch.cat(reach))):
        ends = at < far
        behind = torch.quantile((at - depth)[ends], QUANTILES).tolist()
        print(
            f"rays that {name}: {100 * ends.float().mean():.1f} %, that far behind the "
            f"rendered depth: " + " / ".join(f"{b:.2f}" for b in behind)
        )


if __name__ == "__main__":
    main()
