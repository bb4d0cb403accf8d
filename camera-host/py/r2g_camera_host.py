"""The camera host: one camera's real frames into an r2g instance's camera services (see
camera-host/README.md). Started by `r2g up` (or the unit r2g-camera@NAME.CAMERA) for each
camera the robot config names:

    r2g_camera_host.py --instance NAME --camera CAM --driver realsense --serial S
                       [--width 640 --height 480 --fps 30] [--no-depth]
    r2g_camera_host.py ... --driver uvc --device /dev/video0          (RGB only)
    r2g_camera_host.py ... --driver replay --replay frames.npz         (no hardware)
                       [--frames N] [--stats-json PATH]                (benches)

`realsense` opens the device's colour (RGB8) and depth (Z16) streams through librealsense2 (the
pyrealsense2 wheel), pairs them in a `rs.syncer`, reprojects depth into the colour image with
`rs.align(rs.stream.color)` and scales it to metres. `replay` is the same code with the device
replaced by librealsense's software device, fed from an .npz by a thread at --fps (layout in
README-host.md): everything after the device is the RealSense path. `uvc` reads a V4L2 device
through linuxpy (YUYV, or MJPG when Pillow is installed; no depth; not verified here: no V4L2
device can be made on these machines).

Prints `CAMERA READY <camera>` after the first frame is published. Exit codes: 0 on
SIGTERM/SIGINT or after --frames; 1 an unexpected failure while running (the runtime went away);
2 a configuration it cannot use (no such device, no calibration, the instance not running,
a bad replay file); 3 the camera delivers frames of another size than configured (its
calibration no longer applies). A camera that stops delivering frames does not end the host: it
says so and reopens the device every second; nothing stale is ever published.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import select
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

STALL_S = 2.0  # no frame for this long: the camera stopped
RETRY_S = 1.0  # then reopen it this often
MAX_W, MAX_H = 640, 480

STOP = False


def _stop(*_: object) -> None:
    global STOP
    STOP = True


class ConfigError(Exception):
    """Exit 2: a configuration this host cannot use (or, while reconnecting, a device not back)."""


class SizeChanged(Exception):
    """Exit 3: frames of another size than configured."""


def monotonic_from_system_ms(t_ms: float) -> int:
    """A system-clock (CLOCK_REALTIME) time in ms as CLOCK_MONOTONIC ns, by the offset between the
    two clocks now."""
    offset = time.time_ns() - time.monotonic_ns()
    return int(round(t_ms * 1e6)) - offset


class Source:
    """One camera. `open()` starts it (ConfigError if it cannot), `read(timeout_s)` returns the
    newest frame as (rgb, depth_m or None, (fx, fy, cx, cy) or None, captured_ns, time_domain)
    or None when none came in time (SizeChanged when its size is not the configured one),
    `close()` stops it; it can be opened again. The arrays stay valid until the next read() or
    close() (they may be views of the driver's buffers)."""

    what = "camera"  # the device, for messages
    problem: str | None = None  # why frames stopped, when known (said with the stall)

    def open(self) -> None:
        raise NotImplementedError

    def read(self, timeout_s: float):
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def __iter__(self):
        """Frames until the camera has none for STALL_S (TimeoutError); open it first."""
        while True:
            f = self.read(STALL_S)
            if f is None:
                raise TimeoutError(f"no frame for {STALL_S:.0f} s from {self.what}")
            yield f


# ---- librealsense: a real device, or the software device; one path after that ----

def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise ConfigError(f"pyrealsense2 is not installed ({e}); requirements.txt pins it")
    return rs


class RealSenseSource(Source):
    """Colour (RGB8) and, unless depth=False, depth (Z16) of one librealsense device: each
    sensor opened on its profiles and started into one syncer; framesets without both streams
    are skipped; depth reprojected into the colour camera by rs.align (skipped when the two
    streams already share a camera: same intrinsics, identity extrinsics) and scaled to metres
    with the depth sensor's depth scale."""

    def __init__(self, width: int, height: int, fps: int, depth: bool, serial: str | None = None) -> None:
        self.width, self.height, self.fps, self.depth = width, height, fps, depth
        self.serial = serial
        self.what = f"RealSense {serial}"
        self.sensors: list = []
        self.sync = None
        self.align = None
        self.held = None
        self.incomplete = 0  # framesets without both streams, skipped

    # The device: a real one found by serial; ReplaySource hands over a software device.
    def device(self):
        rs = _rs()
        found = {}
        for d in rs.context().query_devices():
            try:
                found[d.get_info(rs.camera_info.serial_number)] = d
            except RuntimeError:
                continue  # a device that went away while listed
        if self.serial not in found:
            listed = ", ".join(f"{s} ({found[s].get_info(rs.camera_info.name)})" for s in sorted(found))
            raise ConfigError(f"no RealSense with serial {self.serial} (found: {listed or 'none'})")
        return found[self.serial]

    def _pick(self, sensors, stream, fmt, size):
        """(sensor index, profile) of `stream` in `fmt` at the fps: at `size`, or for depth (size
        None) the size nearest the colour image's."""
        best = None
        for i, s in enumerate(sensors):
            for p in s.get_stream_profiles():
                if p.stream_type() != stream or p.format() != fmt or p.fps() != self.fps or not p.is_video_stream_profile():
                    continue
                v = p.as_video_stream_profile()
                wh = (v.width(), v.height())
                if size is not None and wh != size:
                    continue
                cost = abs(wh[0] - self.width) + abs(wh[1] - self.height)
                if best is None or cost < best[0]:
                    best = (cost, i, p)
        if best is None:
            at = f"{size[0]}x{size[1]}" if size else "any size"
            offered = sorted({f"{p.as_video_stream_profile().width()}x{p.as_video_stream_profile().height()}"
                              f"@{p.fps()}" for s in sensors for p in s.get_stream_profiles()
                              if p.stream_type() == stream and p.format() == fmt and p.is_video_stream_profile()})
            raise ConfigError(f"the device offers no {stream.name} {fmt.name} stream at {at} and {self.fps} fps "
                              f"(it offers {', '.join(offered) or 'none'})")
        return best[1], best[2]

    def open(self) -> None:
        self.problem = None
        try:
            self._open()
        except RuntimeError as e:  # librealsense's errors (a device unplugged while opened, busy)
            self.close()
            raise ConfigError(f"cannot start the device: {e}")

    def _open(self) -> None:
        rs = _rs()
        dev = self.device()
        sensors = list(dev.query_sensors())
        ci, cp = self._pick(sensors, rs.stream.color, rs.format.rgb8, (self.width, self.height))
        wanted = {ci: [cp]}
        self.scale = None
        self.align = None
        if self.depth:
            di, dp = self._pick(sensors, rs.stream.depth, rs.format.z16, None)
            wanted.setdefault(di, []).append(dp)  # one sensor may give both (D405)
            ds = sensors[di]
            if not ds.is_depth_sensor():
                raise ConfigError(f"the sensor '{ds.get_info(rs.camera_info.name)}' gives depth but no depth scale")
            self.scale = np.float32(ds.as_depth_sensor().get_depth_scale())
            if not self._same_camera(dp, cp):
                self.align = rs.align(rs.stream.color)
        k = cp.as_video_stream_profile().get_intrinsics()
        self.intrinsics = (k.fx, k.fy, k.ppx, k.ppy)
        self.sync = rs.syncer(2)
        self.sensors = []
        for i, profiles in wanted.items():
            s = sensors[i]
            s.open(profiles if len(profiles) > 1 else profiles[0])
            self.sensors.append(s)
            s.start(self.sync)
        self.dev = dev

    @staticmethod
    def _same_camera(dp, cp) -> bool:
        """Depth already in the colour camera: rs.align would only lose pixels there (rounding
        at pixel borders leaves 2-6 % of them empty), so it is skipped."""
        a, b = dp.as_video_stream_profile().get_intrinsics(), cp.as_video_stream_profile().get_intrinsics()
        e = dp.get_extrinsics_to(cp)
        return ((a.width, a.height) == (b.width, b.height)
                and np.allclose([a.fx, a.fy, a.ppx, a.ppy], [b.fx, b.fy, b.ppx, b.ppy], rtol=0, atol=1e-6)
                and a.model == b.model and np.allclose(a.coeffs, b.coeffs)
                and np.allclose(e.rotation, [1, 0, 0, 0, 1, 0, 0, 0, 1], atol=1e-7)
                and np.allclose(e.translation, 0, atol=1e-7))

    def read(self, timeout_s: float):
        try:
            return self._read(timeout_s)
        except RuntimeError as e:  # librealsense failing mid-stream: no frame, and the reason
            self.problem = f"librealsense: {e}"
            return None

    def _read(self, timeout_s: float):
        rs = _rs()
        ok, fs = self.sync.try_wait_for_frames(max(1, int(timeout_s * 1000)))
        if not ok:
            return None
        # The newest complete set; older ones queued behind it are dropped, never published.
        best = fs if self._complete(fs) else None
        while True:
            nxt = self.sync.poll_for_frames()
            if not nxt:
                break
            if self._complete(nxt):
                best = nxt
            else:
                self.incomplete += 1
        if best is None:
            self.incomplete += 1
            return None
        fs = best
        if self.align is not None:
            fs = self.align.process(fs)
        c = fs.get_color_frame()
        w, h = c.get_width(), c.get_height()
        if (w, h) != (self.width, self.height):
            raise SizeChanged(f"frames of {w}x{h}, configured {self.width}x{self.height}")
        rgb = np.asanyarray(c.get_data())
        if rgb.shape != (h, w, 3) or not rgb.flags.c_contiguous:
            rgb = np.ascontiguousarray(rgb.reshape(h, w, 3))
        depth_m = None
        d = None
        if self.depth:
            d = fs.get_depth_frame()
            z = np.asanyarray(d.get_data())
            depth_m = np.multiply(z, self.scale, dtype=np.float32)  # 0 counts stay 0: no reading
        self.held = (fs, c, d)  # keeps the views' buffers alive until the next read
        captured_ns, domain = self._stamp(rs, c)
        return rgb, depth_m, self.intrinsics, captured_ns, domain

    def _complete(self, fs) -> bool:
        return bool(fs.get_color_frame()) and (not self.depth or bool(fs.get_depth_frame()))

    @staticmethod
    def _stamp(rs, f) -> tuple[int, str]:
        """The colour exposure on CLOCK_MONOTONIC: a global/system-time stamp converted, else the
        frame's arrival (librealsense's arrival metadata if it has it, else now)."""
        domain = f.get_frame_timestamp_domain()
        if domain in (rs.timestamp_domain.global_time, rs.timestamp_domain.system_time):
            return monotonic_from_system_ms(f.get_timestamp()), domain.name
        toa = rs.frame_metadata_value.time_of_arrival
        if f.supports_frame_metadata(toa):
            return monotonic_from_system_ms(f.get_frame_metadata(toa)), "arrival"
        return time.monotonic_ns(), "arrival"

    def close(self) -> None:
        self.held = None
        for s in self.sensors:
            for step in (s.stop, s.close):
                try:
                    step()
                except RuntimeError:
                    pass
        self.sensors = []
        self.sync = None
        self.align = None
        self.dev = None


class ReplaySource(RealSenseSource):
    """The RealSense path on librealsense's software device: a colour sensor (and a depth sensor
    unless depth=False) whose streams carry the .npz's intrinsics, identity extrinsics between
    them, fed in a loop at `fps` by a thread (system-time stamps of the moment each frame is
    fed, as a camera stamps its exposure)."""

    def __init__(self, path: Path, width: int, height: int, fps: int, depth: bool) -> None:
        super().__init__(width, height, fps, depth)
        self.path = Path(path)
        self.what = f"replay {self.path}"
        self.rgb, self.counts, self.k, self.depth_scale = self._load()
        n, h, w, _ = self.rgb.shape
        if (w, h) != (width, height):
            raise SizeChanged(f"the replay's frames are {w}x{h}, configured {width}x{height}")
        if self.counts is None and depth:
            self.depth = False
            self.note = "the replay file has no depth_m: RGB only"
        else:
            self.note = None
        self.feeder = None
        self.stop_feeding = threading.Event()
        self.fed = 0

    def _load(self):
        try:
            with np.load(self.path) as f:
                data = {k: f[k] for k in f.files}
        except Exception as e:  # missing, not an npz, truncated, pickled objects...
            raise ConfigError(f"cannot read the replay file: {type(e).__name__}: {e}")
        keys = set(data)
        missing = [k for k in ("rgb", "fx", "fy", "cx", "cy") if k not in keys]
        if missing:
            raise ConfigError(f"the replay file lacks {', '.join(missing)} (it has {', '.join(sorted(keys))})")
        rgb = data["rgb"]
        if rgb.ndim == 3:
            rgb = rgb[None]
        if rgb.dtype != np.uint8 or rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.shape[0] == 0:
            raise ConfigError(f"rgb must be uint8 (N, H, W, 3) or (H, W, 3), not {rgb.dtype} {rgb.shape}")
        try:
            k = tuple(float(data[c]) for c in ("fx", "fy", "cx", "cy"))
            scale = float(data["depth_scale"]) if "depth_scale" in keys else 0.001
        except (TypeError, ValueError) as e:
            raise ConfigError(f"fx, fy, cx, cy and depth_scale must be scalars ({e})")
        if not (scale > 0 and np.isfinite(scale)):
            raise ConfigError(f"depth_scale must be a positive number of metres per count, not {scale}")
        counts = None
        if "depth_m" in keys:
            d = data["depth_m"]
            if d.ndim == 2:
                d = d[None]
            if d.ndim != 3 or d.shape[1:] != rgb.shape[1:3] or not np.issubdtype(d.dtype, np.floating):
                raise ConfigError(f"depth_m must be float metres (N, H, W) or (H, W) of the rgb's size "
                                  f"{rgb.shape[2]}x{rgb.shape[1]}, not {d.dtype} {d.shape}")
            if d.shape[0] not in (1, rgb.shape[0]):
                raise ConfigError(f"depth_m has {d.shape[0]} frames, rgb {rgb.shape[0]}")
            # Z16 counts; what Z16 cannot hold (NaN, <= 0, beyond 65535 counts) is "no reading".
            c = np.rint(np.asarray(d, dtype=np.float64) / scale)
            counts = np.where(np.isfinite(c) & (c > 0) & (c <= 65535), c, 0).astype(np.uint16)
        return np.ascontiguousarray(rgb), counts, k, scale

    def device(self):
        rs = _rs()
        n, h, w, _ = self.rgb.shape
        k = rs.intrinsics()
        k.width, k.height = w, h
        k.fx, k.fy, k.ppx, k.ppy = self.k
        k.model, k.coeffs = rs.distortion.none, [0.0] * 5

        def stream(kind, fmt, bpp, uid):
            s = rs.video_stream()
            s.type, s.index, s.uid = kind, 0, uid
            s.width, s.height, s.fps, s.bpp, s.fmt, s.intrinsics = w, h, self.fps, bpp, fmt, k
            return s

        dev = rs.software_device()
        dev.register_info(rs.camera_info.name, "r2g replay")
        dev.register_info(rs.camera_info.serial_number, f"replay:{self.path.name}")
        cs = dev.add_sensor("Color")
        self.cprof = cs.add_video_stream(stream(rs.stream.color, rs.format.rgb8, 3, 1), True)
        self.ds = self.dprof = None
        if self.depth:
            ds = dev.add_sensor("Depth")
            self.dprof = ds.add_video_stream(stream(rs.stream.depth, rs.format.z16, 2, 2), True)
            ds.add_read_only_option(rs.option.depth_units, self.depth_scale)  # makes it a depth sensor
            e = rs.extrinsics()
            e.rotation, e.translation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0]
            self.dprof.register_extrinsics_to(self.cprof, e)
            self.ds = ds
        self.cs = cs
        self.sw = dev  # the software device and its sensors must outlive the frames fed to them
        return dev

    def open(self) -> None:
        super().open()
        self.stop_feeding.clear()
        self.feeder = threading.Thread(target=self._feed, name="replay-feeder", daemon=True)
        self.feeder.start()

    def _frame(self, rs, profile, pixels, bpp, t_ms, i):
        # A new software_video_frame per frame: its `pixels` setter copies the array into a
        # buffer that librealsense frees when the frame is released, so one must never be
        # reused (setting pixels again would free that buffer a second time).
        f = rs.software_video_frame()
        f.pixels = pixels
        f.bpp = bpp
        f.stride = bpp * pixels.shape[1]
        f.timestamp = t_ms
        f.domain = rs.timestamp_domain.system_time
        f.frame_number = i
        f.profile = profile.as_video_stream_profile()
        if bpp == 2:
            f.depth_units = self.depth_scale
        return f

    def _feed(self) -> None:
        rs = _rs()
        n = len(self.rgb)
        period = 1.0 / self.fps
        due = time.monotonic()
        i = 0
        try:
            while not self.stop_feeding.is_set():
                t_ms = time.time_ns() / 1e6
                if self.ds is not None:  # depth first: the syncer pairs it with the colour frame
                    d = self.counts[i % len(self.counts)]
                    self.ds.on_video_frame(self._frame(rs, self.dprof, d, 2, t_ms, i))
                self.cs.on_video_frame(self._frame(rs, self.cprof, self.rgb[i % n], 3, t_ms, i))
                i += 1
                self.fed = i
                due += period
                late = time.monotonic() - due
                if late > period:  # fell behind (a stalled machine): drop frames, as a camera would
                    due = time.monotonic()
                self.stop_feeding.wait(max(0.0, due - time.monotonic()))
        except Exception as e:  # reported by the host as a stall, with this reason
            self.problem = f"feeding the software device failed: {type(e).__name__}: {e}"

    def close(self) -> None:
        self.stop_feeding.set()
        if self.feeder is not None:
            self.feeder.join(timeout=2.0)
            self.feeder = None
        super().close()
        self.sw = self.cs = self.ds = None


# ---- UVC through V4L2 (linuxpy); not verified without a device ----

class UvcSource(Source):
    """A UVC camera through V4L2 (linuxpy, memory-mapped buffers): YUYV converted to RGB in
    numpy (BT.601, limited range unless the driver says full), or MJPG decoded by Pillow when
    the camera offers no YUYV. No depth, no intrinsics (they come from the
    calibration file). Capture time: the buffer's timestamp when the driver stamps on
    CLOCK_MONOTONIC (uvcvideo does), else the arrival."""

    def __init__(self, device: str, width: int, height: int, fps: int) -> None:
        self.path, self.width, self.height, self.fps = device, width, height, fps
        self.what = f"V4L2 {device}"
        self.dev = self.cap = None

    def open(self) -> None:
        try:
            from linuxpy.video.device import BufferType, Device, PixelFormat, V4L2Error, VideoCapture
            from linuxpy.video import device as v4l2
        except ImportError as e:
            raise ConfigError(f"the uvc driver needs linuxpy ({e}); requirements.txt pins it")
        if not os.path.exists(self.path):
            raise ConfigError(f"no V4L2 device {self.path}")
        try:
            dev = Device(self.path)
            dev.open()
        except OSError as e:
            raise ConfigError(f"cannot open {self.path}: {e}")
        try:
            cap_t = BufferType.VIDEO_CAPTURE
            offered = {f.pixel_format for f in dev.info.formats if f.type == cap_t}
            if PixelFormat.YUYV in offered:
                fmt = PixelFormat.YUYV
            elif PixelFormat.MJPEG in offered:
                fmt = PixelFormat.MJPEG
                if importlib.util.find_spec("PIL") is None:
                    raise ConfigError(f"{self.path} offers MJPG but not YUYV; decoding MJPG needs Pillow, "
                                      "which is not installed")
            else:
                raise ConfigError(f"{self.path} offers neither YUYV nor MJPG "
                                  f"({', '.join(sorted(p.name for p in offered)) or 'no capture format'})")
            dev.set_format(cap_t, self.width, self.height, int(fmt))
            got = dev.get_format(cap_t)
            if (got.width, got.height) != (self.width, self.height):
                raise ConfigError(f"{self.path} gives {got.width}x{got.height} {fmt.name}, "
                                  f"not the configured {self.width}x{self.height}")
            try:
                dev.set_fps(cap_t, self.fps)
            except OSError:
                pass  # some cameras have a fixed rate
            raw = v4l2.get_raw_format(dev, cap_t)
            self.full_range = raw.fmt.pix.quantization == 1  # V4L2_QUANTIZATION_FULL_RANGE
            self.stride = got.bytes_per_line or self.width * 2
            self.buf = bytearray(max(got.size, self.stride * self.height))  # one frame, copied out of the driver's
            self.yuyv = fmt == PixelFormat.YUYV
            cap = VideoCapture(dev)
            cap.open()
        except ConfigError:
            dev.close()
            raise
        except (OSError, V4L2Error) as e:
            dev.close()
            raise ConfigError(f"cannot start {self.path}: {e}")
        self.dev, self.cap, self.v4l2, self.V4L2Error = dev, cap, v4l2, V4L2Error
        self.problem = None

    def read(self, timeout_s: float):
        try:
            return self._read(timeout_s)
        except (OSError, self.V4L2Error) as e:  # e.g. ENODEV: unplugged
            self.problem = f"V4L2: {e}"
            return None

    def _read(self, timeout_s: float):
        ready, _, _ = select.select([self.dev], [], [], timeout_s)
        if not ready:
            return None
        arrival = time.monotonic_ns()
        src = self.cap.buffer
        # Copied out while the buffer is dequeued: the driver refills it once it is queued again.
        frame = src.raw_read(into=self.buf) if isinstance(src, self.v4l2.MemoryMap) else src.raw_read()
        data = frame.data
        b = frame.buff
        if (b.flags & 0xE000) == 0x2000:  # V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC
            captured, domain = b.timestamp.secs * 1_000_000_000 + b.timestamp.usecs * 1000, "v4l2_monotonic"
        else:
            captured, domain = arrival, "arrival"
        if self.yuyv:
            rgb = self._yuyv(data, len(data))
        else:
            rgb = self._mjpg(bytes(data))
        return rgb, None, None, captured, domain

    def _yuyv(self, data, nbytes: int) -> np.ndarray:
        w, h = self.width, self.height
        if nbytes < self.stride * h:
            raise SizeChanged(f"a frame of {nbytes} bytes, a {w}x{h} YUYV frame has {self.stride * h}")
        px = np.frombuffer(data, dtype=np.uint8, count=self.stride * h).reshape(h, self.stride)[:, :w * 2]
        px = px.reshape(h, w // 2, 4).astype(np.float32)  # Y0 U Y1 V: two pixels share U and V
        y = px[..., 0::2]  # (h, w/2, 2): the pair's two lumas
        u = px[..., 1:2] - 128.0  # (h, w/2, 1): broadcast over the pair
        v = px[..., 3:4] - 128.0
        if self.full_range:
            kr, kgu, kgv, kb = 1.402, 0.344, 0.714, 1.772
        else:
            y = (y - 16.0) * 1.164
            kr, kgu, kgv, kb = 1.596, 0.392, 0.813, 2.017
        rgb = np.empty((h, w // 2, 2, 3), dtype=np.float32)
        rgb[..., 0] = y + kr * v
        rgb[..., 1] = y - (kgu * u + kgv * v)
        rgb[..., 2] = y + kb * u
        np.clip(rgb, 0, 255, out=rgb)
        return np.rint(rgb, out=rgb).astype(np.uint8).reshape(h, w, 3)

    def _mjpg(self, data: bytes) -> np.ndarray:
        import io
        import PIL.Image

        img = PIL.Image.open(io.BytesIO(data)).convert("RGB")
        if img.size != (self.width, self.height):
            raise SizeChanged(f"frames of {img.size[0]}x{img.size[1]}, configured {self.width}x{self.height}")
        return np.asarray(img)

    def close(self) -> None:
        for step in ((self.cap.close if self.cap else None), (self.dev.close if self.dev else None)):
            if step is None:
                continue
            try:
                step()
            except (OSError, ValueError):
                pass
        self.cap = self.dev = None


# ---- the host ----

class Latencies:
    """Capture → published, µs, over the last `n` frames (a long-running host stays bounded)."""

    def __init__(self, n: int = 1 << 17) -> None:
        self.v = np.empty(n)
        self.count = 0

    def add(self, us: float) -> None:
        self.v[self.count % len(self.v)] = us
        self.count += 1

    def summary(self) -> dict:
        v = self.v[:min(self.count, len(self.v))]
        if not len(v):
            return {"p50": None, "p99": None, "max": None}
        return {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99)), "max": float(v.max())}


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description="Publishes one camera's frames into an r2g instance's camera services")
    ap.add_argument("--instance", required=True)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--driver", choices=["realsense", "uvc", "replay"], required=True)
    ap.add_argument("--serial", help="realsense: the device's serial number")
    ap.add_argument("--device", help="uvc: the V4L2 node, e.g. /dev/video0")
    ap.add_argument("--replay", type=Path, help="replay: the .npz to feed the software device")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--fps", type=int, default=30)
    ap.add_argument("--no-depth", action="store_true")
    ap.add_argument("--frames", type=int, default=0, help="stop after this many published frames (benches)")
    ap.add_argument("--stats-json", type=Path, help="on exit, write the run's figures here")
    a = ap.parse_args(argv)
    need = {"realsense": "serial", "uvc": "device", "replay": "replay"}[a.driver]
    if getattr(a, need) is None:
        ap.error(f"--driver {a.driver} needs --{need}")
    if not (0 < a.width <= MAX_W and 0 < a.height <= MAX_H) or a.fps <= 0:
        ap.error(f"--width/--height at most {MAX_W}x{MAX_H} and --fps > 0 (got {a.width}x{a.height} at {a.fps})")
    return a


def make_source(a: argparse.Namespace) -> Source:
    if a.driver == "realsense":
        return RealSenseSource(a.width, a.height, a.fps, not a.no_depth, serial=a.serial)
    if a.driver == "replay":
        return ReplaySource(a.replay, a.width, a.height, a.fps, not a.no_depth)
    return UvcSource(a.device, a.width, a.height, a.fps)


class Host:
    def __init__(self, a: argparse.Namespace) -> None:
        self.a = a
        self.what = {"realsense": f"RealSense {a.serial}", "uvc": f"V4L2 {a.device}", "replay": f"replay {a.replay}"}[a.driver]
        self.lat = Latencies()
        self.published = 0
        self.t_first = self.t_last = None
        self.domain = None
        self.stalls = 0
        self.source: Source | None = None

    def say(self, text: str) -> None:
        print(f"r2g-camera {self.a.camera} ({self.what}): {text}", file=sys.stderr, flush=True)

    def run(self) -> int:
        a = self.a
        try:
            import r2g_camera
        except ImportError as e:
            self.say(f"the publisher module r2g_camera is missing ({e}); make builds it")
            return 2
        try:
            pub = r2g_camera.Publisher(a.instance, a.camera)
        except (ValueError, RuntimeError) as e:
            self.say(str(e))
            return 2
        try:
            return self._serve(pub)
        finally:
            try:
                pub.close()
            except (ValueError, RuntimeError):
                pass

    def _serve(self, pub) -> int:
        a = self.a
        if pub.width is not None and (pub.width, pub.height) != (a.width, a.height):
            self.say(f"the calibration is for {pub.width}x{pub.height} images, the camera is configured for "
                     f"{a.width}x{a.height}")
            return 2
        if a.driver == "uvc" and pub.intrinsics is None:
            self.say("a UVC camera reports no intrinsics: give fx, fy, cx, cy in its calibration file")
            return 2
        try:
            src = self.source = make_source(a)
            src.open()
        except ConfigError as e:
            self.say(str(e))
            return 2
        except SizeChanged as e:
            self.say(f"{e}: its calibration does not apply; not starting (exit 3)")
            return 3
        note = getattr(src, "note", None)
        if note:
            self.say(note)
        try:
            return self._loop(pub, src)
        except SizeChanged as e:
            self.say(f"{e}: its calibration no longer applies; stopping (exit 3)")
            return 3
        finally:
            src.close()

    def _loop(self, pub, src: Source) -> int:
        a = self.a
        opened = True
        since = time.monotonic()  # of the last frame, or of (re)opening
        stalled_at = None
        next_try = 0.0
        last_reason = None
        while not STOP:
            now = time.monotonic()
            if not opened:
                if now < next_try:
                    time.sleep(min(0.1, next_try - now))
                    continue
                next_try = now + RETRY_S
                try:
                    src.open()
                except ConfigError as e:
                    if str(e) != last_reason:
                        self.say(f"not back yet: {e}; trying every {RETRY_S:.0f} s")
                        last_reason = str(e)
                    continue
                opened, since = True, time.monotonic()
            frame = src.read(0.1)
            if frame is None:
                if time.monotonic() - since >= STALL_S:
                    why = src.problem
                    if stalled_at is None:
                        self.stalls += 1
                        stalled_at = since
                        self.say(f"no frame for {STALL_S:.0f} s{f' ({why})' if why else ''}; "
                                 f"reopening the device every {RETRY_S:.0f} s, publishing nothing meanwhile")
                    src.close()
                    opened, last_reason = False, None
                    next_try = time.monotonic() + RETRY_S
                continue
            since = time.monotonic()
            if stalled_at is not None:
                self.say(f"frames again after {since - stalled_at:.1f} s")
                stalled_at = None
            rgb, depth_m, k, captured_ns, domain = frame
            fx, fy, cx, cy = pub.intrinsics if pub.intrinsics is not None else k
            try:
                info = pub.publish(rgb, depth_m, fx, fy, cx, cy, captured_ns)
            except ValueError as e:
                self.say(f"the publisher refused a frame: {e}")
                return 2
            except RuntimeError as e:
                self.say(f"publishing failed: {e}")
                return 1 if self.published else 2
            t = time.monotonic()
            self.lat.add((info["published_ns"] - captured_ns) / 1e3)
            self.published += 1
            self.t_last = t
            if self.t_first is None:
                self.t_first = t
                print(f"CAMERA READY {a.camera}", flush=True)
            if domain != self.domain:
                self.say(f"exposure times from the {domain} clock")
                self.domain = domain
            if a.frames and self.published >= a.frames:
                break
        return 0

    def stats(self) -> dict:
        span = (self.t_last - self.t_first) if self.t_first is not None else 0.0
        src = self.source
        return {"camera": self.a.camera, "driver": self.a.driver, "device": self.what,
                "frames": self.published,
                "fps": (self.published - 1) / span if self.published > 1 and span > 0 else 0.0,
                "capture_to_published_us": self.lat.summary(),
                "latency_frames": min(self.lat.count, len(self.lat.v)),
                "time_domain": self.domain, "stalls": self.stalls,
                "incomplete_framesets": getattr(src, "incomplete", 0) if src else 0}

    def write_stats(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.stats(), indent=1) + "\n")
        os.replace(tmp, path)


def main(argv=None) -> int:
    a = parse_args(argv)
    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    host = Host(a)
    try:
        code = host.run()
    except Exception as e:  # never a traceback: the camera, the device and what went wrong
        host.say(f"unexpected failure: {type(e).__name__}: {e}")
        code = 1
    if a.stats_json:
        try:
            host.write_stats(a.stats_json)
        except OSError as e:
            host.say(f"cannot write {a.stats_json}: {e}")
    return code


if __name__ == "__main__":
    sys.exit(main())
