"""``aefabmap publish``: publish frames (image directory, video file or camera) on a zenoh key.

Every frame carries a JSON attachment ``{"seq", "stamp_ns", "src"}`` so the node can count
dropped frames (see aefabmap_runtime.adapters.zenoh_transport).
"""

from __future__ import annotations

import argparse
import json
import logging
import threading

from aefabmap.cli.options import add_zenoh_options
from aefabmap_runtime.errors import AefabmapError

log = logging.getLogger("aefabmap.publish")


def register(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "publish",
        help="publish frames from images, a video or a camera",
        description="Publish frames as JPEG/PNG on a zenoh key at a fixed rate (JPEG/PNG files are sent as they are).",
    )
    frames = p.add_argument_group("frames (one source)")
    src = frames.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", metavar="DIR", help="directory of .jpg/.png images (sorted by name)")
    src.add_argument("--video", metavar="FILE", help="video file")
    src.add_argument("--camera", type=int, metavar="N", help="camera index (OpenCV)")
    frames.add_argument("--loop", action="store_true", help="start again at the end of the images/video")
    frames.add_argument("--count", type=int, default=None, metavar="N", help="stop after N frames")
    out = p.add_argument_group("publishing (Zenoh)")
    out.add_argument("--key", required=True, metavar="KEY", help="zenoh image key, e.g. robot/camera/image")
    out.add_argument("--rate", required=True, type=float, metavar="HZ", help="frames per second")
    add_zenoh_options(p, out, config=False)
    p.set_defaults(func=main)
    return p


def main(args: argparse.Namespace) -> int:
    from aefabmap_runtime.adapters.node import stop_on_signals
    from aefabmap_runtime.adapters.node_session import warn_exposure
    from aefabmap_runtime.adapters.zenoh_transport import cli_session_config
    from aefabmap_runtime.tools.publisher import (
        camera_source,
        images_dir_source,
        publish_frames,
        video_source,
    )

    stop = threading.Event()
    try:
        session = cli_session_config("connect", connect=args.connect, listen=args.listen,
                                     allow_exposure=args.allow_exposure)
        warn_exposure(session, log)
        if args.images is not None:
            source = images_dir_source(args.images)
        elif args.video is not None:
            source = video_source(args.video)
        else:
            source = camera_source(args.camera)
        with stop_on_signals(stop):
            summary = publish_frames(
                session, args.key, source, rate_hz=args.rate, count=args.count, loop=args.loop, stop_event=stop
            )
    except AefabmapError as exc:
        log.error("%s", exc)
        return exc.exit_code
    if not summary.matched:
        log.warning("no subscriber on %s was seen before publishing started", args.key)
    print(json.dumps(summary.__dict__))
    return 0
