"""Spin until Ctrl-C or SIGTERM, for the node, the demo driver and the viewer: every way rclpy reports a stop is a
normal stop (exit status 0); and the node's threads' scheduling while it spins."""
from __future__ import annotations

import os


def spin_until_shutdown(spin) -> None:
    """Call `spin()` (an executor's or rclpy's spin) and return when a signal stops it.

    rclpy's signal handler shuts the context down; depending on where the executor is at that moment, spin raises
    KeyboardInterrupt, ExternalShutdownException, or - between two waits, or while a message is taken - an
    RCLError (a RuntimeError) about the invalid context. Any other error, or one while the context is still valid,
    propagates. After such an RCLError the same SIGINT's KeyboardInterrupt (rclpy's handler chains Python's) is
    still pending and lands while the RCLError is handled: it is caught there too, else it would end a clean stop
    with a traceback and exit status -2.
    """
    import rclpy
    from rclpy.executors import ExternalShutdownException

    try:
        try:
            spin()
        except RuntimeError:
            if rclpy.ok():
                raise
    except (KeyboardInterrupt, ExternalShutdownException):
        pass


def run_publisher(node) -> int:
    """Spin a publishing node (the demo drivers) until a signal, or until a callback raises SystemExit (its code is
    returned); the node and the context are shut down either way."""
    import rclpy

    code = 0
    try:
        spin_until_shutdown(lambda: rclpy.spin(node))
    except SystemExit as done:
        code = int(done.code or 0)
    finally:
        node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    return code


def set_realtime_priority(priority: int, logger) -> bool:
    """SCHED_FIFO at `priority` for the calling thread only (the executor's; the DDS threads keep the normal
    scheduler and run while it waits between ticks). Returns whether it took; a refusal is logged with the remedy."""
    if priority <= 0:
        return False
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError) as error:
        logger.warning(f"realtime_priority {priority}: not allowed ({error.strerror or error}); running with the "
                       "normal scheduler. Grant CAP_SYS_NICE (e.g. docker --cap-add SYS_NICE) or an rtprio limit "
                       "(ulimit -r, /etc/security/limits.conf)")
        return False
    logger.info(f"executor thread at SCHED_FIFO priority {priority}")
    return True


def raise_receive_threads(thread_ids, priority: int, logger) -> int:
    """SCHED_FIFO at `priority` (above the executor's) for the node's own DDS threads: they receive only the poses
    answered on arrival and other low-rate input, and hand them over without waiting for the end of a tick.
    Returns how many threads took it."""
    raised = 0
    for tid in thread_ids:
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            raised += 1
        except (PermissionError, OSError):
            continue  # ended meanwhile, or refused like the executor's would have been
    logger.info(f"{raised} DDS receive threads of the node's own participant at SCHED_FIFO priority {priority}")
    return raised
