"""The camera host: one camera's real frames into an r2g instance's camera services (see
camera-host/README.md). Started by `r2g up` (or the unit r2g-camera@NAME.CAMERA) for each
camera the robot config names:

    r2g_camera_host.py --instance NAME --camera CAM --driver realsense --serial S
                       [--width 640 --height 480 --fps 30] [--no-depth]
    r2g_camera_host.py ... --driver uvc --device /dev/video0          (RGB only)
    r2g_camera_host.py ... --driver replay --replay frames.npz         (no hardware)

`realsense` opens the device's colour and depth sensors through librealsense2 (the pyrealsense2
wheel), pairs their frames and reprojects depth into the colour image (metres). `replay` is the
same code with the device replaced by librealsense's software device, fed from an .npz (`rgb`
(N,H,W,3) or (H,W,3) uint8, optional `depth_m` float32 of the same height and width, `fx`,
`fy`, `cx`, `cy`, optional `depth_scale` (0.001)): everything after the device is the RealSense
path. `uvc` reads a V4L2 device with linuxpy if it is installed (not verified here: no V4L2
device can be made on these machines).

Prints `CAMERA READY <camera>` after the first frame is published. Exit codes: 0 on
SIGTERM/SIGINT, 2 for a configuration it cannot use (no such device, no calibration, the
instance not running), 3 when the camera delivers frames of another size than configured (its
calibration no longer applies). A camera that stops delivering frames does not end the host: it
says so and reopens the device every second; nothing stale is ever published.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

STOP = False


def _stop(*_: object) -> None:
    global STOP
    STOP = True


class ConfigError(Exception):
    """Exit 2: a configuration this host cannot use."""


class SizeChanged(Exception):
    """Exit 3: frames of another size than configured."""


class Stalled(Exception):
    """No frame for a while: reopen the device."""


def say(camera: str, text: str) -> None:
    print(f"r2g-camera {camera}: {text}", file=sys.stderr, flush=True)


# ---- depth into the colour image ----

class Aligner:
    """Reprojects a depth image into the colour camera (intrinsics of both, extrinsics from depth
    to colour): each depth pixel is lifted to 3D, moved into the colour frame and projected; the
    nearest point wins where several land on one pixel."""

    def __init__(self, depth_k, color_k, rot_colmajor, trans, size_c) -> None:
        (self.fxd, self.fyd, self.cxd, self.cyd, self.wd, self.hd) = depth_k
        (self.fxc, self.fyc, self.cxc, self.cyc) = color_k
        self.R = np.asarray(rot_colmajor, dtype=np.float64).reshape(3, 3).T
        self.t = np.asarray(trans, dtype=np.float64)
        self.wc, self.hc = size_c
        u, v = np.meshgrid(np.arange(self.wd), np.arange(self.hd))
        self.rx = ((u - self.cxd) / self.fxd).ravel()
        self.ry = ((v - self.cyd) / self.fyd).ravel()
        self.identity = (
            np.allclose(self.R, np.eye(3)) and np.allclose(self.t, 0)
            and (self.wd, self.hd) == (self.wc, self.hc)
            and np.allclose([self.fxd, self.fyd, self.cxd, self.cyd], [self.fxc, self.fyc, self.cxc, self.cyc])
        )

    def __call__(self, z: np.ndarray) -> np.ndarray:
        if self.identity:
            return np.ascontiguousarray(z, dtype=np.float32)
        zf = z.ravel().astype(np.float64)
        ok = zf > 0
        p = np.stack([self.rx[ok] * zf[ok], self.ry[ok] * zf[ok], zf[ok]])
        q = self.R @ p + self.t[:, None]
        front = q[2] > 1e-6
        q = q[:, front]
        uc = np.rint(self.fxc * q[0] / q[2] + self.cxc).astype(np.int64)
        vc = np.rint(self.fyc * q[1] / q[2] + self.cyc).astype(np.int64)
        inside = (uc >= 0) & (uc < self.wc) & (vc >= 0) & (vc < self.hc)
        uc, vc, zc = uc[inside], vc[inside], q[2][inside]
        order = np.argsort(-zc)  # farthest first: the nearest is written last
        out = np.zeros((self.hc, self.wc), dtype=np.float32)
        out[vc[order], uc[order]] = zc[order]
        return out


# ---- librealsense: a real device or the software device, one path after that ----

class RealSense:
    """Colour (RGB8) and depth (Z16) sensors of one librealsense device, each into its own frame
    queue; frames paired by time, depth reprojected into colour, in metres."""

    def __init__(self, camera: str, width: int, height: int, fps: int, depth: bool, device=None,
                 serial: str | None = None, feeder=None, sensors=None, depth_scale=None) -> None:
        import pyrealsense2 as rs

        self.rs, self.camera, self.fps, self.feeder = rs, camera, fps, feeder
        if device is None:
            found = {d.get_info(rs.camera_info.serial_number): d for d in rs.context().query_devices()}
            if serial not in found:
                raise ConfigError(f"no RealSense with serial {serial} (found: {', '.join(found) or 'none'})")
            device = found[serial]
        self.device = device
        # A real device names its sensors; the software device's are handed over as they are.
        color_sensor, depth_sensor = sensors or (device.first_color_sensor(), device.first_depth_sensor() if depth else None)
        self.color_sensor = color_sensor
        self.cp = self._profile(self.color_sensor, rs.stream.color, rs.format.rgb8, width, height, fps)
        self.depth_sensor = depth_sensor if depth else None
        self.cq = rs.frame_queue(2, keep_frames=True)
        self.dq = rs.frame_queue(2, keep_frames=True) if depth else None
        ci = self.cp.as_video_stream_profile().get_intrinsics()
        self.intrinsics = (ci.fx, ci.fy, ci.ppx, ci.ppy)
        if depth:
            self.dp = self._profile(self.depth_sensor, rs.stream.depth, rs.format.z16, None, None, fps)
            di = self.dp.as_video_stream_profile().get_intrinsics()
            ext = self.dp.get_extrinsics_to(self.cp)
            self.scale = depth_scale if depth_scale is not None else self.depth_sensor.as_depth_sensor().get_depth_scale()
            self.align = Aligner((di.fx, di.fy, di.ppx, di.ppy, di.width, di.height), self.intrinsics,
                                 ext.rotation, ext.translation, (width, height))
            self.depth_sensor.open(self.dp)
            self.depth_sensor.start(self.dq)
        self.color_sensor.open(self.cp)
        self.color_sensor.start(self.cq)
        self.width, self.height = width, height
        self.last_depth = None

    def _profile(self, sensor, stream, fmt, width, height, fps):
        best = None
        for p in sensor.get_stream_profiles():
            v = p.as_video_stream_profile()
            if p.stream_type() != stream or p.format() != fmt or p.fps() != fps:
                continue
            if width is not None and (v.width(), v.height()) != (width, height):
                continue
            # Depth: the mode nearest the colour image's size.
            if best is None or (width is None and abs(v.width() - self.width_hint) < abs(best.as_video_stream_profile().width() - self.width_hint)):
                best = p
        if best is None:
            what = f"{width}x{height}" if width else "any size"
            raise ConfigError(f"the device offers no {stream} {fmt} mode at {what} and {fps} fps")
        return best

    width_hint = 640

    def stamp_ns(self, frame) -> tuple[int, str]:
        """The exposure on CLOCK_MONOTONIC: global/system-time stamps converted, else now."""
        rs = self.rs
        domain = frame.get_frame_timestamp_domain()
        if domain in (rs.timestamp_domain.system_time, rs.timestamp_domain.global_time):
            offset = time.time_ns() - time.monotonic_ns()
            return int(frame.get_timestamp() * 1e6) - offset, "device"
        return time.monotonic_ns(), "arrival"

    def read(self, timeout_s: float = 2.0):
        if self.feeder is not None:
            self.feeder()
        try:
            c = self.cq.wait_for_frame(int(timeout_s * 1000))
        except RuntimeError:
            raise Stalled(f"no colour frame for {timeout_s:.0f} s")
        v = c.as_video_frame()
        if (v.get_width(), v.get_height()) != (self.width, self.height):
            raise SizeChanged(f"frames of {v.get_width()}x{v.get_height()}, configured {self.width}x{self.height}")
        rgb = np.asanyarray(v.get_data()).reshape(self.height, self.width, 3).copy()
        depth_m = None
        if self.dq is not None:
            # The depth frame nearest in time (within half a frame period), waiting at most one.
            want = c.get_timestamp()
            deadline = time.monotonic() + 1.0 / self.fps
            while True:
                ok, d = self.dq.try_wait_for_frame(5)
                if ok:
                    self.last_depth = d
                if self.last_depth is not None and abs(self.last_depth.get_timestamp() - want) <= 500.0 / self.fps:
                    break
                if time.monotonic() > deadline:
                    break
            d = self.last_depth
            if d is not None and abs(d.get_timestamp() - want) <= 500.0 / self.fps:
                z = np.asanyarray(d.as_depth_frame().get_data()).astype(np.float32) * np.float32(self.scale)
                depth_m = self.align(z)
        captured_ns, domain = self.stamp_ns(c)
        return rgb, depth_m, self.intrinsics, captured_ns, domain

    def close(self) -> None:
        for s in (self.color_sensor, self.depth_sensor):
            if s is None:
                continue
            try:
                s.stop()
                s.close()
            except RuntimeError:
                pass


def software_device(camera: str, path: Path, width: int, height: int, fps: int, depth: bool) -> RealSense:
    """librealsense's software device fed from an .npz: the RealSense path without hardware."""
    import pyrealsense2 as rs

    try:
        data = np.load(path)
    except (OSError, ValueError) as e:
        raise ConfigError(f"cannot read the replay file {path}: {e}")
    rgb = np.asarray(data["rgb"], dtype=np.uint8)
    rgb = rgb[None] if rgb.ndim == 3 else rgb
    depth_m = data["depth_m"] if "depth_m" in data else None
    if depth_m is not None:
        depth_m = np.asarray(depth_m, dtype=np.float32)
        depth_m = depth_m[None] if depth_m.ndim == 2 else depth_m
    scale = float(data["depth_scale"]) if "depth_scale" in data else 0.001
    n, h, w, _ = rgb.shape
    intr = rs.intrinsics()
    intr.width, intr.height = w, h
    intr.fx, intr.fy, intr.ppx, intr.ppy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
    intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
    dev = rs.software_device()
    ds = dev.add_sensor("Depth") if depth else None
    cs = dev.add_sensor("Color")

    def stream(kind, fmt, bpp, uid):
        s = rs.video_stream()
        s.type, s.index, s.uid, s.width, s.height, s.fps, s.bpp, s.fmt, s.intrinsics = kind, 0, uid, w, h, fps, bpp, fmt, intr
        return s

    cp = cs.add_video_stream(stream(rs.stream.color, rs.format.rgb8, 3, 1), True)
    dp = None
    if depth:
        dp = ds.add_video_stream(stream(rs.stream.depth, rs.format.z16, 2, 0), True)
        ds.add_read_only_option(rs.option.depth_units, scale)
        ext = rs.extrinsics()
        ext.rotation, ext.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
        dp.register_extrinsics_to(cp, ext)
    counts = (np.rint(depth_m / scale).clip(0, 65535).astype(np.uint16) if depth_m is not None else None)
    state = {"i": 0, "next": time.monotonic()}

    def feed() -> None:
        # One frame per call at the configured rate, as a camera would deliver them.
        time.sleep(max(0.0, state["next"] - time.monotonic()))
        state["next"] = max(state["next"] + 1.0 / fps, time.monotonic())
        i = state["i"]
        state["i"] += 1
        t_ms = time.time_ns() / 1e6
        if dp is not None and counts is not None:
            f = rs.software_video_frame()
            f.pixels, f.bpp, f.stride = np.ascontiguousarray(counts[i % len(counts)]), 2, 2 * w
            f.timestamp, f.domain, f.frame_number = t_ms, rs.timestamp_domain.system_time, i
            f.profile, f.depth_units = dp.as_video_stream_profile(), scale
            ds.on_video_frame(f)
        g = rs.software_video_frame()
        g.pixels, g.bpp, g.stride = np.ascontiguousarray(rgb[i % n]), 3, 3 * w
        g.timestamp, g.domain, g.frame_number = t_ms, rs.timestamp_domain.system_time, i
        g.profile = cp.as_video_stream_profile()
        cs.on_video_frame(g)

    if (w, h) != (width, height):
        raise SizeChanged(f"the replay's frames are {w}x{h}, configured {width}x{height}")
    cam = RealSense(camera, width, height, fps, depth and dp is not None, device=dev, feeder=feed,
                    sensors=(cs, ds), depth_scale=scale)
    cam._keep = (dev, ds, cs)  # the software sensors must outlive their frames
    return cam


class Uvc:
    """A UVC camera through V4L2 (linuxpy), YUYV converted to RGB. Not verified without a device."""

    def __init__(self, camera: str, device: str, width: int, height: int, fps: int) -> None:
        try:
            from linuxpy.video.device import Device, PixelFormat  # type: ignore
        except ImportError:
            raise ConfigError("the uvc driver needs linuxpy (pip install linuxpy), which is not installed")
        if not os.path.exists(device):
            raise ConfigError(f"no V4L2 device {device}")
        self.dev = Device(device)
        self.dev.open()
        self.dev.set_format(1, width, height, PixelFormat.YUYV)  # 1: video capture buffer type
        self.dev.set_fps(1, fps)
        self.frames = iter(self.dev)
        self.width, self.height = width, height
        self.intrinsics = None

    def read(self, timeout_s: float = 2.0):
        f = next(self.frames)
        if (f.width, f.height) != (self.width, self.height):
            raise SizeChanged(f"frames of {f.width}x{f.height}, configured {self.width}x{self.height}")
        yuyv = np.frombuffer(f.data, dtype=np.uint8).reshape(self.height, self.width // 2, 4).astype(np.float32)
        y = np.stack([yuyv[..., 0], yuyv[..., 2]], axis=-1).reshape(self.height, self.width)
        u = np.repeat(yuyv[..., 1], 2, axis=1) - 128.0
        v = np.repeat(yuyv[..., 3], 2, axis=1) - 128.0
        rgb = np.stack([y + 1.402 * v, y - 0.344 * u - 0.714 * v, y + 1.772 * u], axis=-1)
        return np.clip(rgb, 0, 255).astype(np.uint8), None, self.intrinsics, time.monotonic_ns(), "arrival"

    def close(self) -> None:
        self.dev.close()


def main() -> int:
    ap = argparse.ArgumentParser(description="Publishes one camera's frames into an r2g instance")
    ap.add_argument("--instance", required=True)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--driver", choices=["realsense", "uvc", "replay"], required=True)
    ap.add_argument("--serial")
    ap.add_argument("--device")
    ap.add_argument("--replay", type=Path)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--fps", type=int, default=30)
    ap.add_argument("--no-depth", action="store_true")
    ap.add_argument("--frames", type=int, default=0, help="stop after this many frames (benches)")
    ap.add_argument("--stats-json", type=Path, help="write the run's figures here on exit")
    a = ap.parse_args()
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    cam_name = a.camera
    try:
        import r2g_camera
    except ImportError as e:
        say(cam_name, f"the publisher module r2g_camera is missing ({e}): make builds it")
        return 2
    try:
        pub = r2g_camera.Publisher(a.instance, cam_name)
    except (ValueError, RuntimeError) as e:
        say(cam_name, str(e))
        return 2
    if pub.width is not None and (pub.width, pub.height) != (a.width, a.height):
        say(cam_name, f"the calibration is for {pub.width}x{pub.height} images, the camera is configured for "
                      f"{a.width}x{a.height}")
        return 2

    def open_camera():
        if a.driver == "realsense":
            return RealSense(cam_name, a.width, a.height, a.fps, not a.no_depth, serial=a.serial)
        if a.driver == "replay":
            return software_device(cam_name, a.replay, a.width, a.height, a.fps, not a.no_depth)
        return Uvc(cam_name, a.device, a.width, a.height, a.fps)

    lat_us: list[float] = []
    published, t_first, ready, cam = 0, None, False, None
    domain_seen = None
    code = 0
    try:
        while not STOP:
            if cam is None:
                try:
                    cam = open_camera()
                except ConfigError as e:
                    if a.driver != "realsense" or "no RealSense" not in str(e) or not ready:
                        say(cam_name, str(e))
                        code = 2
                        break
                    say(cam_name, f"{e}; trying again in 1 s")
                    time.sleep(1)
                    continue
            try:
                rgb, depth_m, intr, captured_ns, domain = cam.read()
            except Stalled as e:
                say(cam_name, f"{e} from {a.driver} {a.serial or a.device or a.replay}; reopening every second")
                cam.close()
                cam = None
                time.sleep(1)
                continue
            if intr is None:
                intr = pub.intrinsics
                if intr is None:
                    say(cam_name, "a UVC camera reports no intrinsics: give them in its calibration file")
                    code = 2
                    break
            fx, fy, cx, cy = intr
            info = pub.publish(rgb, depth_m, fx, fy, cx, cy, captured_ns)
            lat_us.append((info["published_ns"] - captured_ns) / 1e3)
            if domain != domain_seen:
                say(cam_name, f"exposure times from the {domain} clock")
                domain_seen = domain
            published += 1
            if t_first is None:
                t_first = time.monotonic()
            if not ready:
                print(f"CAMERA READY {cam_name}", flush=True)
                ready = True
            if a.frames and published >= a.frames:
                break
    except SizeChanged as e:
        say(cam_name, f"{e}: its calibration no longer applies; stopping (exit 3)")
        code = 3
    except (ValueError, RuntimeError) as e:
        say(cam_name, str(e))
        code = 2 if not ready else 1
    finally:
        if cam is not None:
            cam.close()
        pub.close()
    if a.stats_json:
        lat = np.array(lat_us) if lat_us else np.zeros(1)
        span = (time.monotonic() - t_first) if t_first else 0.0
        stats = {"camera": cam_name, "frames": published,
                 "fps": (published - 1) / span if published > 1 and span > 0 else 0.0,
                 "capture_to_published_us": {"p50": float(np.percentile(lat, 50)),
                                             "p99": float(np.percentile(lat, 99)), "max": float(lat.max())}}
        tmp = a.stats_json.with_suffix(".tmp")
        tmp.write_text(json.dumps(stats))
        tmp.replace(a.stats_json)
    return code


if __name__ == "__main__":
    sys.exit(main())
