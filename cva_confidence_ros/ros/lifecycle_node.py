"""The managed (lifecycle) variant of the confidence node, for robots that bring nodes up with a
lifecycle manager (``nav2_lifecycle_manager``, ``ros2 lifecycle set``, a launch file's
``LifecycleNode`` actions).

Same topics, parameters, threads and diagnostics as :class:`ConfidenceNode`; the work is split
over the standard transitions (``lifecycle_msgs``):

* *unconfigured* (start): parameters are declared and can be set; nothing else runs;
* ``configure``: builds the pipeline (weights loaded, matcher warmed up), the publishers, the
  diagnostics timer and the worker thread. A configuration it refuses (weights missing for the
  matcher and depth, a device that is not there, …) fails the transition with the reason in the
  log, and the node stays *unconfigured* for another try with other parameters;
* ``activate``: subscribes to the four inputs, and the output publishers (lifecycle publishers)
  publish;
* ``deactivate``: unsubscribes; a frame waiting is dropped, a frame in progress finishes
  unpublished; pairing starts afresh on the next activate;
* ``cleanup``: stops the worker and releases the pipeline, back to *unconfigured*;
* ``shutdown``: all of the above from any state.

``autostart: true`` (start-up only) configures and activates at once, for use without a
lifecycle manager.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter

from cva_confidence_ros.errors import CVAError
from cva_confidence_ros.ros.common import QOS_OVERRIDES, run_node, warn_unknown_parameters
from cva_confidence_ros.ros.confidence_node import NODE_NAME, ConfidenceCore

__all__ = ['AUTOSTART', 'ManagedConfidenceNode', 'run']

#: The managed node's own parameter: configure and activate at start-up.
AUTOSTART = 'autostart'
_AUTOSTART_DESCRIPTION = (
    'Configure and activate at start-up, without a lifecycle manager (start-up only).'
)


class ManagedConfidenceNode(ConfidenceCore, LifecycleNode):
    """The confidence node as a ROS 2 managed node; see the module docstring for its states.

    Args:
        context: rclpy context (tests use one per node); None = the global one.
        parameter_overrides: Start-up parameter values, as with ``--ros-args -p``.
        **kwargs: Passed on to :class:`rclpy.lifecycle.LifecycleNode`.
    """

    def __init__(
        self,
        *,
        context: Context | None = None,
        parameter_overrides: list[Parameter] | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(
            NODE_NAME, context=context, parameter_overrides=parameter_overrides, **kwargs
        )
        try:
            self._init_core()
            self.declare_parameter(
                AUTOSTART,
                False,
                ParameterDescriptor(description=_AUTOSTART_DESCRIPTION, read_only=True),
            )
            warn_unknown_parameters(self)
            if self.get_parameter(AUTOSTART).value:
                if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
                    self.trigger_activate()
        except BaseException:
            # A start-up value of the wrong type (-p max_disparity:=abc): destroyed here, as
            # ConfidenceNode is, not left to the garbage collector, which would unregister the
            # /rosout publisher of its name, by then perhaps a later node's.
            if hasattr(self, '_mailbox'):
                self.destroy_node()
            else:  # refused while declaring its parameters
                Node.destroy_node(self)
                self._state_machine.destroy_when_not_in_use()
            raise

    def summary(self) -> str:
        """One line on the node's state (and, once configured, what it computes)."""
        state = self._state_machine.current_state[1]
        if not self.configured:
            return f'{state}; lifecycle transitions: configure, then activate'
        return f'{state}; {super().summary()}'

    # Transitions --------------------------------------------------------------------------

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except CVAError as error:
            # Raised while building the pipeline or the publishers (a bad qos_overrides
            # value), before anything is kept.
            self.get_logger().error(
                f'configure failed: {error}; still unconfigured (set other parameters and '
                'configure again)'
            )
            return TransitionCallbackReturn.FAILURE
        except Exception as error:  # noqa: BLE001  (rclpy would turn it into a silent ERROR)
            self.get_logger().error(f'configure raised {type(error).__name__}: {error}')
            return TransitionCallbackReturn.ERROR  # on_error releases what was made
        self.get_logger().info(f'configured: {super().summary()}')
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._activate()
        except CVAError as error:
            # A bad qos_overrides value of an input (read-only: fix the parameter file).
            self.get_logger().error(f'activate failed: {error}; still inactive')
            return TransitionCallbackReturn.FAILURE
        result = super().on_activate(state)  # enables the lifecycle publishers
        self.get_logger().info('active: subscribed to the stereo inputs')
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._deactivate()
        self.get_logger().info('inactive: unsubscribed from the stereo inputs')
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._cleanup()
        self.get_logger().info('cleaned up: pipeline released')
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.configured:
            self._cleanup()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        # A transition raised: release what there is, back to unconfigured.
        if self.configured:
            self._cleanup()
        return TransitionCallbackReturn.SUCCESS

    def destroy_node(self) -> None:
        """Stop the worker and destroy the node, its lifecycle state machine included.

        rclpy's own ``destroy_node`` leaves the state machine, which holds the node's handle:
        the node then ends only when the garbage collector gets to it, and ending it there
        unregisters the ``/rosout`` publisher of its name, which by then may be a later node's
        of the same name (whose log lines then never reach ``/rosout``).
        """
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()

    def _create_output_publisher(self, msg_type: type, topic: str, qos: Any) -> Any:
        return self.create_lifecycle_publisher(
            msg_type, topic, qos, qos_overriding_options=QOS_OVERRIDES
        )

    def destroy_publisher(self, publisher: Any) -> bool:
        # Lifecycle publishers also leave the node's managed entities.
        self._managed_entities.discard(publisher)
        return super().destroy_publisher(publisher)


def run(argv: Sequence[str] | None = None) -> int:
    """Run the managed node until Ctrl-C or SIGTERM (the body of
    :func:`cva_confidence_ros.node.lifecycle_main`)."""
    return run_node(ManagedConfidenceNode, NODE_NAME, argv)
