"""A still of a dimslam-viewer recording, for machines without a display (and for docs/).

Reads an .rrd written by `dimslam-viewer --save` (or `dimslam run --rerun-save`) back with
rerun's own reader and draws what the viewer shows at the end of the run, side by side: the
newest camera image, the newest keyframe's rendered depth, and the tracked path (orange) with
the aligned ground truth (blue) and the keyframes (white) from above (x right, z up the page).

    python benchmarks/rrd_preview.py RUN.rrd --out docs/viewer.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

PANEL = 320


def _last(rows: dict[str, list[dict]], entity: str, column: str):
    """The newest non-empty value of `column` logged on `entity` (by frame), or None."""
    found = [r for r in rows.get(entity, []) if r.get(column)]
    if not found:
        return None
    return max(found, key=lambda r: r.get("frame") or -1)[column]


def read(path: Path) -> dict[str, list[dict]]:
    """Every row of the recording, by entity: `{column: value}` dicts."""
    from rerun.chunk import RrdReader

    rows: dict[str, list[dict]] = {}
    for chunk in RrdReader(path).stream():
        rows.setdefault(chunk.entity_path, []).extend(chunk.to_record_batch().to_pylist())
    return rows


def _panel(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    scale = PANEL / max(h, w)
    resized = cv2.resize(image, (round(w * scale), round(h * scale)), cv2.INTER_NEAREST)
    out = np.zeros((PANEL, PANEL, 3), np.uint8)
    y0, x0 = (PANEL - resized.shape[0]) // 2, (PANEL - resized.shape[1]) // 2
    out[y0 : y0 + resized.shape[0], x0 : x0 + resized.shape[1]] = resized
    return out


def _depth(rows: dict[str, list[dict]]) -> np.ndarray | None:
    buffer = _last(rows, "/keyframe/depth", "DepthImage:buffer")
    fmt = _last(rows, "/keyframe/depth", "DepthImage:format")
    if buffer is None or fmt is None:
        return None
    fmt = fmt[0]
    depth = np.frombuffer(bytes(buffer[0]), np.float32).reshape(fmt["height"], fmt["width"])
    scaled = np.clip(255 * (depth - depth.min()) / max(np.ptp(depth), 1e-6), 0, 255)
    return cv2.applyColorMap(scaled.astype(np.uint8), cv2.COLORMAP_VIRIDIS)


def _top_view(rows: dict[str, list[dict]]) -> np.ndarray:
    out = np.zeros((PANEL, PANEL, 3), np.uint8)
    paths = []
    for entity, colour in (
        ("/world/ground_truth", (255, 160, 0)),
        ("/world/trajectory", (0, 120, 255)),
    ):
        strips = _last(rows, entity, "LineStrips3D:strips")
        if strips:
            paths.append((np.asarray(strips[0], np.float64), colour))
    keyframes = [
        np.asarray(_last(rows, e, "Transform3D:translation")[0])
        for e in rows
        if e.startswith("/world/keyframes/") and _last(rows, e, "Transform3D:translation")
    ]
    points = [p for p, _ in paths] + ([np.array(keyframes)] if keyframes else [])
    if not points:
        return out
    xz = np.concatenate(points)[:, [0, 2]]
    lo, span = xz.min(0), max(np.ptp(xz, axis=0).max(), 1e-6)

    def pixel(p: np.ndarray) -> np.ndarray:
        uv = 20 + (p[:, [0, 2]] - lo) / span * (PANEL - 40)
        return np.stack([uv[:, 0], PANEL - uv[:, 1]], 1).round().astype(np.int32)

    for p, colour in paths:
        cv2.polylines(out, [pixel(p)], False, colour, 2, cv2.LINE_AA)
    for uv in pixel(np.array(keyframes)) if keyframes else []:
        cv2.circle(out, tuple(int(v) for v in uv), 3, (255, 255, 255), -1, cv2.LINE_AA)
    return out


def preview(path: Path) -> np.ndarray:
    """The three panels of the recording at its end, as one BGR image."""
    rows = read(path)
    jpeg = _last(rows, "/world/camera/image", "EncodedImage:blob")
    image = None
    if jpeg is not None:
        image = cv2.imdecode(np.frombuffer(bytes(jpeg[0]), np.uint8), cv2.IMREAD_COLOR)
    depth = _depth(rows)
    blank = np.zeros((PANEL, PANEL, 3), np.uint8)
    panels = [
        blank if image is None else _panel(image),
        blank if depth is None else _panel(depth),
        _top_view(rows),
    ]
    return np.concatenate(panels, axis=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rrd", type=Path, help="recording written by dimslam-viewer --save")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args()
    if not args.rrd.is_file():
        parser.error(f"{args.rrd}: no such file")
    cv2.imwrite(str(args.out), preview(args.rrd))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
