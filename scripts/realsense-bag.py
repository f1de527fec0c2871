#!/usr/bin/env python3
"""Records frames into a librealsense .bag with librealsense's own recorder.

usage: realsense-bag.py FRAMES_DIR OUT.bag

FRAMES_DIR is what b2b_sim::d435::write_recording lays out: manifest.json (the
colour and depth streams' intrinsics, depth_from_colour, the depth unit, and per
frame its stream, number, timestamp and raw file) and the raw frames. A software
device with a depth sensor and a colour sensor stands in for the camera; the
recorder wraps it and writes what its sensors deliver, so librealsense reads the
file back as it would a recording of a D4xx. Needs pyrealsense2 (scripts/setup-realsense).
"""
import json
import os
import sys
import time

import numpy as np
import pyrealsense2 as rs


def fail(msg):
    print(f"realsense-bag: {msg}", file=sys.stderr)
    sys.exit(1)


def intrinsics(m, what):
    try:
        i = rs.intrinsics()
        i.width, i.height = int(m["width"]), int(m["height"])
        i.fx, i.fy, i.ppx, i.ppy = (float(m[k]) for k in ("fx", "fy", "cx", "cy"))
        i.model = rs.distortion.brown_conrady
        i.coeffs = [float(v) for v in m["dist"]]
        return i
    except (KeyError, TypeError, ValueError) as e:
        fail(f"manifest.json: {what} intrinsics: {e!r}")


def stream(kind, fmt, bpp, uid, m, fps, what):
    s = rs.video_stream()
    s.type, s.fmt, s.bpp, s.index, s.uid = kind, fmt, bpp, 0, uid
    s.width, s.height, s.fps = int(m["width"]), int(m["height"]), int(round(fps))
    s.intrinsics = intrinsics(m, what)
    return s


def main():
    if len(sys.argv) != 3:
        fail("usage: realsense-bag.py FRAMES_DIR OUT.bag")
    src, out = sys.argv[1], sys.argv[2]
    try:
        with open(os.path.join(src, "manifest.json")) as f:
            man = json.load(f)
    except (OSError, ValueError) as e:
        fail(f"{os.path.join(src, 'manifest.json')}: {e}")
    fps = float(man["fps"])
    dev = rs.software_device()
    depth_sensor = dev.add_sensor("Stereo Module")
    colour_sensor = dev.add_sensor("RGB Camera")
    dm, cm = man["depth"], man["colour"]
    depth_profile = depth_sensor.add_video_stream(
        stream(rs.stream.depth, rs.format.z16, 2, 0, dm, fps, "depth"))
    colour_profile = colour_sensor.add_video_stream(
        stream(rs.stream.color, rs.format.rgb8, 3, 1, cm, fps, "colour"))
    depth_sensor.add_read_only_option(rs.option.depth_units, float(man["depth_unit_m"]))
    # librealsense's extrinsics: p_to = R p_from + t, R column-major.
    e = rs.extrinsics()
    r = man["depth_from_colour"]["rotation"]  # row-major
    e.rotation = [float(r[3 * j + i]) for i in range(3) for j in range(3)]
    e.translation = [float(v) for v in man["depth_from_colour"]["translation_m"]]
    colour_profile.register_extrinsics_to(depth_profile, e)
    recorder = rs.recorder(out, dev)
    depth_sensor.open(depth_profile)
    colour_sensor.open(colour_profile)
    queue = rs.frame_queue(1000)
    depth_sensor.start(queue)
    colour_sensor.start(queue)
    time.sleep(0.2)  # the recorder drops what arrives before its sensors are ready
    # librealsense plays a recording at the pace it was recorded (the time each
    # frame reached the recorder), not by the frames' timestamps: deliver them
    # at the pace their timestamps say.
    frames = sorted(man["frames"], key=lambda fr: float(fr["timestamp_ms"]))
    for i, fr in enumerate(frames):
        path = os.path.join(src, fr["file"])
        f = rs.software_video_frame()
        if fr["stream"] == "depth":
            m, dtype, bpp, profile, sensor = dm, np.uint16, 2, depth_profile, depth_sensor
        elif fr["stream"] == "colour":
            m, dtype, bpp, profile, sensor = cm, np.uint8, 3, colour_profile, colour_sensor
        else:
            fail(f"manifest.json: frame {fr}: unknown stream")
        w, h = int(m["width"]), int(m["height"])
        data = np.fromfile(path, dtype=np.dtype(dtype).newbyteorder("<"))
        if data.size != w * h * (3 if bpp == 3 else 1):
            fail(f"{path}: {data.size} values, a {w}x{h} {fr['stream']} frame needs {w * h * (3 if bpp == 3 else 1)}")
        f.pixels = data.reshape((h, w, 3) if bpp == 3 else (h, w))
        f.stride, f.bpp = w * bpp, bpp
        f.timestamp = float(fr["timestamp_ms"])
        f.domain = rs.timestamp_domain.system_time
        f.frame_number = int(fr["number"])
        f.profile = profile.as_video_stream_profile()
        if bpp == 2:
            f.depth_units = float(man["depth_unit_m"])
        sensor.on_video_frame(f)
        if i + 1 < len(frames):
            time.sleep(max(0.0, float(frames[i + 1]["timestamp_ms"]) - float(fr["timestamp_ms"])) / 1000.0)
    time.sleep(0.2)
    for s in (depth_sensor, colour_sensor):
        s.stop()
        s.close()
    del recorder
    print(out)


if __name__ == "__main__":
    main()
