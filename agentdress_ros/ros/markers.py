"""The node's Markers (RViz), built on a thread of their own: a Marker costs milliseconds of Python per garment."""
from __future__ import annotations

import rclpy

from .jobs import LatestJobThread
from .messages import make_marker

MARKER_COLORS = ((0.2, 0.45, 0.85, 1.0), (0.25, 0.25, 0.3, 1.0), (0.85, 0.4, 0.2, 1.0), (0.9, 0.75, 0.6, 1.0))


class MarkerThread:
    """Builds and publishes the newest job handed over by `submit` on its own thread; a thread that died of
    something its loop does not catch is started again by the next `submit` (counted, warned)."""

    def __init__(self, node):
        self.node = node  # its stats, warn, report_error, publish_lock and context
        self.thread = LatestJobThread("agentdress-marker", self._publish_job,
                                      lambda error: node.report_error("marker_thread", error),
                                      lambda: rclpy.ok(context=node.context))

    def submit(self, job: list):
        """Executor thread: `job` [(publisher getter, {garment: (vertices, faces)}, stamp, frame_id)] replaces the
        one not yet taken."""
        if self.thread.submit(job):
            self.node.stats.counts["marker_restarts"] += 1
            self.node.warn("marker_thread", "the marker thread had died: restarted")

    def _publish_job(self, job: list):
        for publisher, frames, stamp, frame_id in job:
            self._publish(publisher, frames, stamp, frame_id)

    def _publish(self, publisher, frames, stamp, frame_id):
        """One Marker per garment of `frames` {name: (vertices, faces)} on `publisher()` (looked up under the lock:
        None once the publisher is gone)."""
        for i, (name, (vertices, faces)) in enumerate(frames.items()):
            marker = make_marker(vertices, faces, name, i, frame_id, stamp, MARKER_COLORS[i % len(MARKER_COLORS)])
            with self.node.publish_lock:
                pub = publisher()
                if pub is not None:
                    pub.publish(marker)
