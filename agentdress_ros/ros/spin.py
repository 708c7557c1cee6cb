"""Spin until Ctrl-C or SIGTERM, for the node, the demo driver and the viewer: every way rclpy reports a stop is a
normal stop (exit status 0)."""
from __future__ import annotations


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
