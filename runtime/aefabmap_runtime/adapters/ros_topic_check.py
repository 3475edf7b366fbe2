"""Is the run's ROS 2 image topic published? Said once in the log and on every status answer.

A ``--ros-topic`` that nobody publishes leaves a node at "processed 0" with nothing else to tell:
CHECK_AFTER_S seconds after the node subscribed (at the first turn of its loop after that, a
tenth of a second at most), when no image arrived and no publisher of the topic is in the graph,
the node logs ONE warning naming the sensor_msgs Image and CompressedImage topics that are
published (from the graph's liveliness tokens: rmw_zenoh's, or zenoh-bridge-ros2dds's). From
then on each status answer says whether the topic is published and lists those topics; when the
topic comes (an image, or its publisher), one info line says so.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from aefabmap_runtime.adapters.rmw_zenoh import TopicPublisher
from aefabmap_runtime.adapters.ros_cdr import COMPRESSED_IMAGE_TYPE, IMAGE_TYPE

#: Seconds after the node subscribed before an unpublished topic is reported: the graph's
#: tokens arrive within milliseconds of joining it, a camera node started with the run has
#: had time to declare its publisher.
CHECK_AFTER_S = 3.0
#: Image topics named in a warning at most (the rest are counted).
MAX_LISTED = 8
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)
log = logging.getLogger("aefabmap.ros")


def topic_lines(publishers: list[TopicPublisher]) -> list[str]:
    """``/camera/image_raw (sensor_msgs/msg/Image)`` for each distinct image topic, sorted; the
    place is named when it is not the run's own (``in domain 3``)."""
    return sorted({f"{p.topic} ({p.ros_type})" + (f" in {p.where}" if p.where else "") for p in publishers})


class ImageTopicCheck:
    """Whether ``topic`` is published, from the graph (``publishers()``: the publishers alive,
    each with its ``where``; those whose ``where`` is ``home`` are the run's own domain or bridge)
    and from the images received (``received()``). ``poll()`` from the node's loop logs the
    warning once; ``published()``, ``image_topics()`` and ``warnings()`` answer the status.
    """

    def __init__(self, topic: str, publishers: Callable[[], list[TopicPublisher]], received: Callable[[], int], *,
                 home: str, hint: str, after_s: float = CHECK_AFTER_S, clock: Callable[[], float] = time.monotonic):
        self.topic, self.home, self.hint = topic, home, hint
        self._publishers, self._received, self._clock = publishers, received, clock
        self.due = clock() + after_s
        self.after_s = after_s
        self._next = self.due
        self._warned = False
        self._cleared = False

    def published(self) -> bool | None:
        """True once an image arrived or a publisher of the topic is in the graph; False when
        neither, CHECK_AFTER_S after start; None before then."""
        if self._received() > 0 or any(p.topic == self.topic and p.where == self.home for p in self._publishers()):
            return True
        return None if self._clock() < self.due else False

    def image_topics(self) -> list[str]:
        """The Image and CompressedImage topics published now: the run's domain or bridge first
        (without a place), then the others with theirs."""
        pubs = [p for p in self._publishers() if p.ros_type in IMAGE_TYPES]
        home = topic_lines([TopicPublisher(p.topic, p.ros_type, "") for p in pubs if p.where == self.home])
        return home + topic_lines([p for p in pubs if p.where != self.home])

    def warnings(self) -> list[str]:
        """The warning line while the topic is not published (after CHECK_AFTER_S), else none."""
        if self.published() is not False:
            return []
        topics = self.image_topics()
        listed = ", ".join(topics[:MAX_LISTED]) + (f" and {len(topics) - MAX_LISTED} more"
                                                   if len(topics) > MAX_LISTED else "")
        others = f"image topics published: {listed}" if topics else \
            "no sensor_msgs Image or CompressedImage topic is published at all"
        return [f"ROS 2 topic {self.topic} has no publisher in {self.home} and no image came in "
                f"{self.after_s:g} s; {others}: check --ros-topic{self.hint}"]

    def poll(self) -> None:
        """Log the warning once when the topic is not published at CHECK_AFTER_S, and one info
        line when it comes later (a clock read between checks, which are a second apart)."""
        now = self._clock()
        if self._cleared or now < self._next:
            return
        self._next = now + 1.0
        lines = self.warnings()
        if lines and not self._warned:
            self._warned = True
            log.warning("%s", lines[0])
        elif not lines:
            if self._warned:
                log.info("ROS 2 topic %s is published now", self.topic)
            self._cleared = True
