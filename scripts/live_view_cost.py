"""What the Foxglove live view costs the frame loop: the caller's time in LiveView.on_frame per
frame (thumbnails, annotations, the camera image for a viewer), over a sequence's frames with
the detector's real results, with no viewer, a viewer speaking foxglove.sdk.v1, or one speaking
only foxglove.websocket.v1, subscribed to the view's channels (docs/streaming.md).

    taskset -c 1 python scripts/live_view_cost.py --model BUNDLE --images DIR --viewer sdk

Prints one JSON line: frames timed (after a warm-up), median and p95 ms.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

import numpy as np

from aefabmap_runtime.adapters.bundle_reader import load_detector
from aefabmap_runtime.adapters.foxglove_view import (
    ANNOTATIONS_TOPIC,
    IMAGE_TOPIC,
    PLACE_IMAGE_TOPIC,
    RESULT_TOPIC,
    FoxgloveServer,
    LiveView,
)
from aefabmap_runtime.adapters.frames import ENCODING_JPEG, ENCODING_PNG, decode_image
from aefabmap_runtime.adapters.image_folder import list_images
from aefabmap_runtime.core.detector import DetectorConfig
from aefabmap_runtime.core.verify.verification import VerificationConfig

SUBPROTOCOLS = {"sdk": "foxglove.sdk.v1", "v1": "foxglove.websocket.v1"}
TOPICS = (IMAGE_TOPIC, ANNOTATIONS_TOPIC, PLACE_IMAGE_TOPIC, RESULT_TOPIC)


def connect_viewer(port: int, subprotocol: str, view: LiveView) -> threading.Event:
    """A viewer subscribed to TOPICS that reads everything sent (until the returned event is set)."""
    import websocket  # websocket-client (dev extra)

    ws = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=10, subprotocols=[subprotocol])
    channels: dict[str, int] = {}
    while not set(TOPICS) <= set(channels):
        msg = ws.recv()
        if isinstance(msg, str) and (doc := json.loads(msg)).get("op") == "advertise":
            channels.update({c["topic"]: c["id"] for c in doc["channels"]})
    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": i, "channelId": channels[t]}
                                                              for i, t in enumerate(TOPICS, 1)]}))
    if not view.server.wait_viewer(10):
        raise SystemExit("the viewer's subscription never reached the server")
    stop = threading.Event()

    def drain() -> None:
        while not stop.is_set():
            try:
                ws.recv()
            except Exception:  # noqa: BLE001 - timeouts while nothing is sent
                pass

    threading.Thread(target=drain, daemon=True).start()
    return stop


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--images", required=True, type=Path)
    ap.add_argument("--viewer", choices=("none", "sdk", "v1"), default="sdk")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--warmup", type=int, default=50)
    args = ap.parse_args(argv)
    paths = list_images(args.images)[: args.frames]
    det = load_detector(args.model, DetectorConfig(verification=VerificationConfig(keep_inlier_points=True)))
    view = LiveView(FoxgloveServer(port=0))
    stop = connect_viewer(view.server.port, SUBPROTOCOLS[args.viewer], view) if args.viewer != "none" else None
    ms = []
    for p in paths:
        data = p.read_bytes()
        gray = decode_image(data)
        result = det.process(gray, time.time_ns())
        t0 = time.perf_counter()
        view.on_frame(data, ENCODING_JPEG if p.suffix.lower() in (".jpg", ".jpeg") else ENCODING_PNG, gray, result)
        ms.append((time.perf_counter() - t0) * 1e3)
    if stop is not None:
        stop.set()
    view.close()
    timed = np.asarray(ms[args.warmup:])
    print(json.dumps({"viewer": args.viewer, "frames": int(timed.size), "median_ms": round(float(np.median(timed)), 3),
                      "p95_ms": round(float(np.percentile(timed, 95)), 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
