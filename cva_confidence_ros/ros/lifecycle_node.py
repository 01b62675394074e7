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
  unpublished (one whose outputs are being published is waited for: all of them go out before
  the deactivate ends); pairing starts afresh on the next activate;
* ``cleanup``: stops the worker and releases the pipeline, back to *unconfigured*;
* ``shutdown``: all of the above from any state, to *finalized*, where no transition is left
  and the node is only to be destroyed.

In every state :meth:`~ManagedConfidenceNode.stats`, :meth:`~ManagedConfidenceNode.diagnostics`
and :meth:`~ManagedConfidenceNode.summary` answer; ``pipeline_config`` and ``node_config`` exist
only while configured (*inactive*, *active*) and raise :class:`NotConfiguredError` otherwise.

``autostart: true`` (start-up only) configures and activates at once, for use without a
lifecycle manager.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial
import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter

from cva_confidence_ros.errors import CVAError
from cva_confidence_ros.pipeline import PipelineConfig
from cva_confidence_ros.ros.common import (
    QOS_OVERRIDES,
    diagnostic_status,
    run_node,
    warn_unknown_parameters,
)
from cva_confidence_ros.ros.confidence_node import NODE_NAME, ConfidenceCore, _Stats
from cva_confidence_ros.ros.params import NodeConfig

__all__ = ['AUTOSTART', 'ManagedConfidenceNode', 'NotConfiguredError', 'run']

#: The managed node's own parameter: configure and activate at start-up.
AUTOSTART = 'autostart'
_AUTOSTART_DESCRIPTION = (
    'Configure and activate at start-up, without a lifecycle manager (start-up only).'
)

# What a node that is not configured can do next, by its lifecycle state.
_NEXT = {
    'unconfigured': 'lifecycle transitions: configure, then activate',
    'finalized': 'shut down, no lifecycle transition left: destroy the node',
}


class NotConfiguredError(CVAError, RuntimeError):
    """The managed node was asked for what exists only while it is configured (*inactive* or
    *active*): ``pipeline_config``, ``node_config``."""


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
        service = getattr(self, '_service_change_state', None)  # None: no lifecycle services
        if service is not None:
            service.callback = partial(self._on_change_state, service.callback)
        # On the worker, the mailbox's clears (one a deactivate) when its frame was taken: a
        # frame in progress at a deactivate finishes unpublished, even if activate follows
        # before it ends (it would go out then, an old frame, after pairing started afresh).
        self._frame = threading.local()
        try:
            self._init_core()
            self._stats = _Stats()  # stats() and diagnostics() answer before the first configure
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
        """One line on the node's lifecycle state and, configured, what it computes; not
        configured, what it can do next (*finalized*: nothing, the node is to be destroyed)."""
        state = self._state_label()
        if not self.configured:
            return f'{state}; {_NEXT.get(state, "not configured")}'
        return f'{state}; {super().summary()}'

    # State-aware views ---------------------------------------------------------------------

    @property
    def pipeline_config(self) -> PipelineConfig:
        """The configuration the next frame is processed with.

        Raises:
            NotConfiguredError: The node is not configured (*unconfigured* — before configure
                or after cleanup — or *finalized*): there is no pipeline to describe; the
                values to come are the node's parameters.
        """
        with self._lock:
            if self._pipeline is not None:
                return self._pipeline_config
        raise self._not_configured('pipeline_config')

    @property
    def node_config(self) -> NodeConfig:
        """The node-side configuration in force.

        Raises:
            NotConfiguredError: The node is not configured (as :attr:`pipeline_config`).
        """
        with self._lock:
            if self._pipeline is not None:
                return self._node_config
        raise self._not_configured('node_config')

    def stats(self) -> dict[str, int]:
        """Counters of the current configuration (see :meth:`ConfidenceCore.stats`): zero
        before the first configure; after cleanup or shutdown those of the configuration
        released, until the next configure starts them afresh."""
        return super().stats()

    def diagnostics(self) -> DiagnosticStatus:
        """The node's current ``DiagnosticStatus``.

        *Active*, that of :class:`ConfidenceNode`. *Inactive* (configured, published, but not
        subscribed to the inputs), the same values with the state as the message, not a
        "processing at 0.0 Hz" that reads as a silent camera; level OK unless what is left of
        the last active window says otherwise. Not configured, level ``STALE`` (nothing is
        processed and no ``/diagnostics`` is published, which a diagnostic aggregator shows as
        stale too), the lifecycle state and what it can do next as the message, the state and
        :meth:`stats` as values. Every state gives its name as ``lifecycle_state``.
        """
        state = self._state_label()
        if self.configured:
            status = super().diagnostics()
            status.values.append(KeyValue(key='lifecycle_state', value=state))
            if state == 'inactive' and status.level == DiagnosticStatus.OK:
                status.message = (
                    'inactive: configured, not subscribed to the stereo inputs (activate to '
                    'process)'
                )
            return status
        values: dict[str, object] = {'lifecycle_state': state, **self.stats()}
        message = f'{state}: not processing ({_NEXT.get(state, "not configured")})'
        return diagnostic_status(
            self, 'stereo confidence', DiagnosticStatus.STALE, message, values
        )

    def _state_label(self) -> str:
        return str(self._state_machine.current_state[1])

    def _not_configured(self, what: str) -> NotConfiguredError:
        return NotConfiguredError(
            f'{what} exists only while the node is configured (inactive or active); it is '
            f'{self._state_label()}'
        )

    # Transitions --------------------------------------------------------------------------

    def _on_change_state(
        self, answer: Any, request: ChangeState.Request, response: ChangeState.Response
    ) -> ChangeState.Response:
        """The ``change_state`` service: rclpy's ``answer``, but a transition given by id alone
        (no label) that the current state does not have is refused (``success`` false, as one
        by an unknown label is) and logged, not raised: rclpy's ``RCLError`` ended the
        executor's spin, and with it the node."""
        if not request.transition.label:
            allowed = {
                transition[0]: transition[1]
                for transition in self._state_machine.available_transitions
            }
            if request.transition.id not in allowed:
                offered = ', '.join(f'{label} [{id_}]' for id_, label in allowed.items())
                self.get_logger().warning(
                    f'change_state refused: no transition {request.transition.id} (and no '
                    f'label) from {self._state_label()}; it allows {offered or "none"}'
                )
                response.success = False
                return response
        return answer(request, response)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        before = [*self.publishers, *self.timers]
        try:
            self._configure()
        except CVAError as error:
            # Raised while building the pipeline or the publishers (a bad qos_overrides
            # value), before anything is kept; whatever was made is released all the same.
            self._abandon_configure(before)
            self.get_logger().error(
                f'configure failed: {error}; still unconfigured (set other parameters and '
                'configure again)'
            )
            return TransitionCallbackReturn.FAILURE
        except Exception as error:  # noqa: BLE001  (rclpy would turn it into a silent ERROR)
            self._abandon_configure(before)
            self.get_logger().error(f'configure raised {type(error).__name__}: {error}')
            return TransitionCallbackReturn.ERROR  # on_error: back to unconfigured
        self.get_logger().info(f'configured: {super().summary()}')
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._activate()
        except CVAError as error:
            # A bad qos_overrides value of an input (read-only: fix the parameter file).
            self.get_logger().error(f'activate failed: {error}; still inactive')
            return TransitionCallbackReturn.FAILURE
        except Exception as error:  # noqa: BLE001  (rclpy would turn it into a silent ERROR)
            self.get_logger().error(f'activate raised {type(error).__name__}: {error}')
            return TransitionCallbackReturn.ERROR  # on_error: back to unconfigured
        result = super().on_activate(state)  # enables the lifecycle publishers
        self.get_logger().info('active: subscribed to the stereo inputs')
        return result

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        # The frame in progress, if any, is not published (its outputs being published are
        # waited for: they all go out before, not some after a quick activate).
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

    # Worker side ---------------------------------------------------------------------------

    def _process(self, item: Any, mailbox: Any) -> None:
        # The frame belongs to the activation it was taken in (noted by the mailbox as it was
        # taken, not here after it: a deactivate in between made it the next activation's).
        self._frame.current = mailbox.taken_clears
        self._frame.deactivated = False
        try:
            super()._process(item, mailbox)
        finally:
            self._frame.current = None
            if self._frame.deactivated and not super()._stopping(mailbox):
                # Left unpublished by a deactivate: dropped, as the frame waiting then was
                # (counted nowhere, received ran ahead of the sum of the other counters).
                with self._lock:
                    self._stats.dropped += 1

    def _publish(self, *args: Any) -> None:
        super()._publish(*args)
        # Published: from here on the frame counts as any other, deactivated or not.
        self._frame.current = None

    def _stopping(self, mailbox: Any) -> bool:
        """As the core's, and, inside a frame not yet published, whether the node was
        deactivated since the frame was taken (no lock taken: the core calls it with the lock
        held)."""
        current = getattr(self._frame, 'current', None)
        if current is not None and current != mailbox.clears:
            self._frame.deactivated = True
            return True
        return super()._stopping(mailbox)

    def _abandon_configure(self, before: list[Any]) -> None:
        """Release what a configure that raised had made: the pipeline and the worker once
        kept, and every publisher and timer the node has gained since ``before`` (rclpy
        records them as they are created; the core's ``_owned`` lists them only at the end, so
        that one raising before, ``create_timer`` say, left the publishers behind)."""
        if self.configured:
            self._cleanup()
        for timer in [timer for timer in self.timers if timer not in before]:
            self.destroy_timer(timer)
        for publisher in [publisher for publisher in self.publishers if publisher not in before]:
            self.destroy_publisher(publisher)

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
