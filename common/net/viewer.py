"""`dimslam-viewer`: a running service, live in rerun (`rerun-sdk`, the `[viz]` extra).

A client of the service like `dimslam-poses`: it subscribes to the camera's frames, the
tracker's poses, the mapper's refined keyframes and map snapshots, and logs to rerun

| entity | what | when |
|---|---|---|
| `world/camera`, `.../image` | the newest camera: pose, pinhole, image (JPEG) | every frame |
| `world/trajectory` | the tracked camera positions so far | every tracked frame |
| `world/ground_truth` | the dataset's path (`--gt`), Sim(3)-aligned to it | every 10 poses |
| `world/keyframes/<n>` | each keyframe's frustum at its newest pose | keyframe poses, refinements |
| `keyframe/depth` | the newest keyframe's depth, rendered from the newest map | every snapshot |
| `world/mesh` | the mapper's mesh (`--mesh-every`) | every N snapshots |

on the timelines `frame` (the stream's frame number) and `time` (the frame's own seconds).
The world is the first camera's frame, OpenCV axes (x right, y down, z forward). Rendering
depth needs the map's settings: give the viewer the mapper's `--preset` (and overrides); a
snapshot of other settings is said once and not rendered.

Where it goes: a viewer already running (`rerun`, default address, or `--connect-viewer`),
one it starts (`--spawn`), or a file (`--save FILE.rrd`, for headless machines; open it later
with `rerun FILE.rrd`). The viewer exits at the end of the stream or on SIGINT/SIGTERM, and
flushes the recording either way.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh
import zenoh

from dimslam.common.config import SlamConfig, map_digest
from dimslam.common.errors import DimslamError
from dimslam.common.eval.evaluation import associate, umeyama
from dimslam.common.eval.report import load_ground_truth
from dimslam.common.geometry.camera import Camera
from dimslam.common.io.trajectory import Trajectory
from dimslam.common.map.field import make_field
from dimslam.common.map.render import render_image
from dimslam.common.net.exchange import load_map
from dimslam.common.net.messages import (
    EndOfStream,
    FrameMessage,
    MapSnapshot,
    MessageError,
    PoseMessage,
    decode_or_end,
)
from dimslam.common.net.service import (
    TICK_S,
    add_process_options,
    log_peer,
    positive_int,
    service_main,
)
from dimslam.common.net.transport import Inbox, Keys, Presence, Rejects, Stop, pose_subscriber

log = logging.getLogger("dimslam.common.net.viewer")

DESCRIPTION = (
    "Show a running dimslam service in rerun: camera images, the tracked and ground-truth "
    "trajectories, keyframe frusta, the newest keyframe's rendered depth and the mesh. Needs "
    "the [viz] extra (pip install 'dimslam[viz]')."
)
DEPTH_WIDTH = 80
"""Width of the rendered keyframe depth: a few thousand rays, well under a second on a CPU."""
GT_EVERY = 10
"""Tracked poses between two alignments of the ground truth."""
END_GRACE_S = 2.0
"""How long refinements and the last snapshot are still taken after the end of stream."""
MESH_TIMEOUT_S = 60.0


def _rerun():
    try:
        import rerun
    except ImportError:
        raise DimslamError("the viewer needs rerun-sdk: pip install 'dimslam[viz]'") from None
    return rerun


def _options(p: argparse.ArgumentParser) -> None:
    sink = p.add_mutually_exclusive_group()
    sink.add_argument(
        "--save", type=Path, metavar="FILE", help="write the recording to FILE (.rrd) instead"
    )
    sink.add_argument("--spawn", action="store_true", help="start a rerun viewer and log to it")
    sink.add_argument(
        "--connect-viewer",
        metavar="URL",
        help="log to the rerun viewer at URL (default: a viewer on this machine's default "
        "port, started with `rerun`)",
    )
    p.add_argument(
        "--gt",
        metavar="PATH",
        help="ground truth to show beside the estimate: a dataset folder or a TUM file",
    )
    p.add_argument(
        "--mesh-every",
        type=int,
        default=0,
        metavar="N",
        help="ask the mapper for its mesh every N map snapshots (default 0: never; each costs "
        "the mapper an extraction between rounds)",
    )
    p.add_argument(
        "--count", type=positive_int, metavar="N", help="exit after N poses from the tracker"
    )


def _transform(rr, T_wc: np.ndarray):
    return rr.Transform3D(translation=T_wc[:3, 3], mat3x3=T_wc[:3, :3])


def _pinhole(rr, camera: Camera):
    return rr.Pinhole(
        image_from_camera=camera.K,
        resolution=[camera.width, camera.height],
        camera_xyz=rr.ViewCoordinates.RDF,
    )


class Viewer:
    """Logs what the service publishes to one rerun recording."""

    def __init__(
        self,
        args: argparse.Namespace,
        cfg: SlamConfig,
        device: torch.device,
        session: zenoh.Session,
        keys: Keys,
        stop: Stop,
    ) -> None:
        if args.mesh_every < 0:
            raise DimslamError(f"--mesh-every {args.mesh_every}: give 0 (never) or more")
        self.rr = _rerun()
        rr = self.rr
        self.args = args
        self.cfg = cfg
        self.keys = keys
        self.stop = stop
        self.session = session
        self.gt: Trajectory | None = None
        if args.gt is not None:
            try:
                self.gt = load_ground_truth(args.gt, None)[0]
            except DimslamError as e:  # a dataset without ground truth is still worth watching
                log.warning("%s: showing the estimate only", e)
        self.rec = rr.RecordingStream("dimslam", recording_id=keys.root)
        if args.save is not None:
            args.save.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(args.save)
        elif args.spawn:
            self.rec.spawn()
        else:
            self.rec.connect_grpc(args.connect_viewer)
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        self.digest = map_digest(cfg)
        self.field = make_field(cfg.map, device=device).requires_grad_(False)
        self.camera: Camera | None = None
        self.track: dict[int, PoseMessage] = {}  # frame -> newest pose
        self.rejects = Rejects()
        self.snapshots = 0
        self.images = 0
        self.other_settings_said = False
        self.poses_in = Inbox(4096, "poses")
        self.frames_in = Inbox(64, "frames")
        self.refined_in = Inbox(4096, "keyframes")
        self.maps_in = Inbox(1, "map snapshots")  # newest wins
        stop.watch(self.poses_in)

        def waking(inbox: Inbox):
            def callback(sample: zenoh.Sample) -> None:
                inbox.callback(sample)
                self.poses_in.wake()  # the loop waits on the poses

            return callback

        # Keep references: an unreferenced subscriber is undeclared (zenoh.md trap 4).
        self.subscribers = [
            pose_subscriber(session, keys.poses, self.poses_in.callback),
            session.declare_subscriber(keys.frames, waking(self.frames_in)),
            session.declare_subscriber(keys.keyframes, waking(self.refined_in)),
            session.declare_subscriber(keys.map, waking(self.maps_in)),
        ]
        self.presence = Presence(session, keys, "viewer", on_change=log_peer)

    # -- the loop ---------------------------------------------------------------------------

    def run(self) -> int:
        tracked = 0
        ended_at = None
        while not self.stop:
            payload = self.poses_in.get(TICK_S)
            for frame in self.frames_in.drain():
                self._frame(frame)
            if payload is not None:
                msg = self._decode("poses", payload, PoseMessage)
                if isinstance(msg, EndOfStream):
                    log.info("end of stream after %d poses", tracked)
                    ended_at = time.monotonic()
                elif msg is not None:
                    self._pose(msg)
                    tracked += not msg.lost
            for refined in self.refined_in.drain():
                msg = self._decode("keyframes", refined, PoseMessage)
                if isinstance(msg, PoseMessage):
                    self._pose(msg, refined=True)
            for snap in self.maps_in.drain():
                msg = self._decode("map", snap, MapSnapshot)
                if isinstance(msg, MapSnapshot):
                    self._snapshot(msg)
            if self.args.count is not None and tracked >= self.args.count:
                break
            if ended_at is not None and time.monotonic() - ended_at > END_GRACE_S:
                break
        return 0

    def _decode(self, topic: str, payload: bytes, kind):
        try:
            return decode_or_end(payload, kind)
        except MessageError as e:
            self.rejects(topic, e)
            return None

    def _at(self, seq: int, timestamp: float) -> None:
        self.rec.set_time("frame", sequence=seq)
        self.rec.set_time("time", duration=timestamp)

    # -- what each message shows ------------------------------------------------------------

    def _frame(self, payload: bytes) -> None:
        msg = self._decode("frames", payload, FrameMessage)
        if not isinstance(msg, FrameMessage):
            return
        rr = self.rr
        if self.camera != msg.camera:
            self.camera = msg.camera
            self.rec.log("world/camera/image", _pinhole(rr, msg.camera), static=True)
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(msg.rgb, cv2.COLOR_RGB2BGR))
        if ok:
            self.images += 1
            self._at(msg.seq, msg.timestamp)
            self.rec.log(
                "world/camera/image",
                rr.EncodedImage(contents=jpeg.tobytes(), media_type="image/jpeg"),
            )

    def _pose(self, msg: PoseMessage, refined: bool = False) -> None:
        """A tracked pose moves the camera; a refined one (an older keyframe) only the path."""
        if not msg.supersedes(self.track.get(msg.seq)):
            return
        self.track[msg.seq] = msg
        rr = self.rr
        self._at(msg.seq, msg.timestamp)
        if not refined:
            self.rec.log("world/camera", _transform(rr, msg.T_wc))
        ordered = sorted(self.track.values(), key=lambda m: (m.timestamp, m.seq))
        positions = np.array([m.T_wc[:3, 3] for m in ordered])
        self.rec.log("world/trajectory", rr.LineStrips3D([positions], colors=[[255, 120, 0]]))
        if msg.keyframe:
            path = f"world/keyframes/{msg.seq}"
            self.rec.log(path, _transform(rr, msg.T_wc))
            if self.camera is not None:
                self.rec.log(path, _pinhole(rr, self.camera.resized(DEPTH_WIDTH)))
        if self.gt is not None and len(self.track) % GT_EVERY == 0:
            self._ground_truth(ordered)

    def _ground_truth(self, ordered: list[PoseMessage]) -> None:
        est_ts = np.array([m.timestamp for m in ordered])
        i_est, i_gt = associate(est_ts, self.gt.timestamps)
        if len(i_est) < 3:
            return
        est = np.array([ordered[i].T_wc[:3, 3] for i in i_est])
        to_estimate = umeyama(self.gt.positions[i_gt], est)
        path = to_estimate.apply_points(self.gt.positions)
        self.rec.log("world/ground_truth", self.rr.LineStrips3D([path], colors=[[0, 160, 255]]))

    def _snapshot(self, snap: MapSnapshot) -> None:
        if snap.config != self.digest:
            if not self.other_settings_said:
                log.warning(
                    "the map has other settings than this viewer's (give it the mapper's "
                    "--preset and overrides): its depth is not shown"
                )
                self.other_settings_said = True
            return
        self.snapshots += 1
        load_map(self.field, snap)
        keyframes = [k for k in snap.keyframes if k in snap.poses]
        if keyframes and self.camera is not None:
            newest = max(keyframes)
            T_wc = torch.from_numpy(snap.poses[newest]).float().to(self.field.bound.device)
            camera = self.camera.resized(DEPTH_WIDTH)
            depth, _ = render_image(self.field, camera, T_wc, self.cfg.render)
            pose = self.track.get(newest)
            self._at(newest, pose.timestamp if pose is not None else 0.0)
            self.rec.log("keyframe/depth", self.rr.DepthImage(depth.cpu().numpy(), meter=1.0))
        if self.args.mesh_every and self.snapshots % self.args.mesh_every == 0:
            self._mesh()

    def _mesh(self) -> None:
        for reply in self.session.get(self.keys.query("mesh"), timeout=MESH_TIMEOUT_S):
            if reply.ok is None:
                log.warning("no mesh: %s", reply.err.payload.to_string())
                continue
            mesh = trimesh.load(
                trimesh.util.wrap_as_stream(reply.ok.payload.to_bytes()), file_type="ply"
            )
            colors = getattr(mesh.visual, "vertex_colors", None)
            self.rec.log(
                "world/mesh",
                self.rr.Mesh3D(
                    vertex_positions=mesh.vertices,
                    triangle_indices=mesh.faces,
                    vertex_colors=None if colors is None else np.asarray(colors)[:, :3],
                ),
            )

    def close(self) -> None:
        self.presence.close()
        for subscriber in self.subscribers:
            subscriber.undeclare()
        log.info(
            "shown: %d images, %d poses, %d map snapshots",
            self.images,
            len(self.track),
            self.snapshots,
        )
        self.rec.flush()
        self.rec.disconnect()
        if self.args.save is not None:
            log.info("recording written to %s", self.args.save)


def _build(args, cfg, device, session, keys, stop) -> Viewer:
    return Viewer(args, cfg, device, session, keys, stop)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="dimslam-viewer", description=DESCRIPTION)
    _options(parser)
    add_process_options(parser)
    return service_main(parser, "viewer", _build, lambda args, service: None, argv)


if __name__ == "__main__":
    sys.exit(main())
