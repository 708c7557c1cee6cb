"""The node's inside diagnostic: the last published garments tested against the posed body on a background thread.

It is the test the drapes, the build reports and the evaluation use (garment.inside: generalised winding number,
split into vertices caught where Anny's skinned body overlaps itself and vertices truly through the skin), plus the
share of face centres inside: where skin shows through flat triangles although their vertices are outside. A check
of a 1,200-vertex garment takes ~90 ms, so it runs on its own thread at `inside_check_hz` (off by default). Its
winding-number kernel releases the GIL; its numpy setup (posing the body, clustering its faces) does not, and
delays the ticks around it by a few milliseconds: a diagnostic to switch on while looking.
"""
from __future__ import annotations

import time

import numpy as np

from .jobs import LatestJobThread

__all__ = ["InsideChecker"]


class InsideChecker:
    """submit() a snapshot from the executor thread; the thread checks the newest one; status() for ~/status."""

    def __init__(self, body, on_error):
        from ..body import visible_body

        self.body, self.on_error = body, on_error
        self.ids, self.faces = visible_body(body)
        self.results: dict = {}
        self.checks = 0
        self._shape_key, self._shape = None, None
        # started now, before the node raises its executor thread's priority
        self.thread = LatestJobThread("agentdress-inside", self._check_job, on_error)

    def submit(self, frames: dict, rotvecs, root_translation, beta):
        """frames {name: (vertices (V, 3), faces (F, 3))} published for the pose rotvecs (B, 3), root (3,) and
        shape beta; copies are the caller's (the thread reads them later)."""
        self.thread.submit((frames, np.array(rotvecs, dtype=np.float64),
                            np.array(root_translation, dtype=np.float64), tuple(float(b) for b in beta)))

    def _check_job(self, job):
        self.results = self.check(*job)
        self.checks += 1

    def check(self, frames: dict, rotvecs, root_translation, beta) -> dict:
        """{"garments": {name: shares in %}, "ms", "checked_at"} for one snapshot (see submit)."""
        from ..garment.inside import BodyInside

        start = time.perf_counter()
        if beta != self._shape_key:
            self._shape_key, self._shape = beta, self.body.shape(np.asarray(beta))
        transforms, _ = self.body.pose(self._shape, rotvecs, root_translation)
        test = BodyInside(self.body.posed_vertices(self._shape, transforms)[self.ids], self.faces)
        garments = {}
        for name, (vertices, faces) in frames.items():
            vertices = np.asarray(vertices, dtype=np.float64)
            report = test.report(vertices)
            centres = test.inside(vertices[np.asarray(faces)].mean(axis=1))
            n = max(len(vertices), 1)
            garments[name] = {"vertices_inside_pct": round(100.0 * report["inside_count"] / n, 3),
                              "in_self_overlap_pct": round(100.0 * report["overlap_count"] / n, 3),
                              "truly_inside_pct": round(100.0 * report["truly_inside_count"] / n, 3),
                              "face_centres_inside_pct": round(100.0 * centres.sum() / max(len(faces), 1), 3)}
        return {"garments": garments, "ms": round(1e3 * (time.perf_counter() - start), 1),
                "checked_at": time.monotonic()}

    def status(self) -> dict:
        results = dict(self.results)
        if not results:
            return {"checks": self.checks}
        return {"checks": self.checks, "age_s": round(time.monotonic() - results.pop("checked_at"), 2), **results}

    def stop(self):
        self.thread.stop()
