"""A daemon thread that works on the newest job handed to it (the node's markers and inside diagnostic)."""
from __future__ import annotations

import os
import threading


class LatestJobThread:
    """`submit(job)` from the executor thread; the thread runs `work(job)` on the newest one (a job not yet taken is
    replaced), reports what it raises to `on_error` and goes on. A thread that died of something the loop does not
    catch is started again by the next `submit`, which then returns True. Runs at the normal scheduler even when
    started from a realtime executor thread (a thread inherits its creator's policy)."""

    def __init__(self, name: str, work, on_error, running=lambda: True):
        self.name, self.work, self.on_error, self.running = name, work, on_error, running
        self._job, self._event, self._stopped = None, threading.Event(), False
        self._start()

    def _start(self):
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()

    def submit(self, job) -> bool:
        restarted = not self._thread.is_alive()
        if restarted:
            self._start()
        self._job = job
        self._event.set()
        return restarted

    def _loop(self):
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except (AttributeError, OSError):
            pass
        while not self._stopped and self.running():
            if not self._event.wait(timeout=0.5):
                continue
            self._event.clear()
            job, self._job = self._job, None
            if job is None:
                continue
            try:
                self.work(job)
            except Exception as error:  # the next job is a fresh try; the thread goes on
                self.on_error(error)

    def stop(self):
        self._stopped = True
        self._event.set()
