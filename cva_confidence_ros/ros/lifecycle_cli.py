"""``cva-lifecycle``: the part of ``ros2 lifecycle`` a managed node needs, for installs without
ros2cli (the pip wheels of ROS 2 do not have it).

    cva-lifecycle get /cva_confidence              # current state, e.g. "unconfigured [1]"
    cva-lifecycle list /cva_confidence             # transitions possible from it
    cva-lifecycle set /cva_confidence configure    # a transition, by label

It calls the node's standard ``lifecycle_msgs`` services (``<node>/get_state``,
``<node>/change_state``, ``<node>/get_available_transitions``) as ``ros2 lifecycle`` does, so it
drives any managed node, not only this package's. Exit status: 0 on success, 1 when the node
refused the transition, 2 for bad arguments or a node that does not answer in ``--timeout``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
import contextlib
import os
import signal
import sys
import threading
import time
from typing import Any

__all__ = ['ask', 'bad_node_name', 'call', 'init_rclpy', 'interruptible', 'main', 'node_name']

EXIT_REFUSED = 1
EXIT_NO_ANSWER = 2
#: Seconds to wait for an answer before sending the request again (see :func:`ask`).
ATTEMPT_S = 3.0
#: The state each transition of the standard state machine ends in.
GOALS = {
    'configure': 'inactive',
    'activate': 'active',
    'deactivate': 'inactive',
    'cleanup': 'unconfigured',
    'shutdown': 'finalized',
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cva-lifecycle',
        description='Get or change the state of a ROS 2 managed (lifecycle) node, as '
        '`ros2 lifecycle` does.',
        epilog='Exit codes: 0 done, 1 the node refused the transition, 2 bad arguments or no '
        'answer within --timeout, 130 stopped by Ctrl-C, 143 by SIGTERM.',
    )
    parser.add_argument('--timeout', type=float, default=10.0,
                        help='seconds to wait for the node and its answer (default 10)')
    commands = parser.add_subparsers(dest='command', required=True)
    get = commands.add_parser('get', help="print the node's current state")
    get.add_argument('node', help='node name, e.g. /cva_confidence')
    listing = commands.add_parser('list', help='print the transitions possible from it')
    listing.add_argument('node')
    change = commands.add_parser('set', help='trigger a transition by its label')
    change.add_argument('node')
    change.add_argument('transition', help='configure, activate, deactivate, cleanup, shutdown')
    return parser


class _Terminated(Exception):
    """SIGTERM, raised where the tool is waiting."""


def init_rclpy(prog: str) -> None:
    """``rclpy.init`` for a one-shot tool: without rclpy's signal handlers.

    rclpy's handlers shut the context down on SIGINT and SIGTERM, and the wait under way then
    failed with a traceback (``RCLError: ... rcl node's context is invalid``) and exit status
    1, the status of a refusal by the node; :func:`interruptible` handles both signals.
    """
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    # The command line is argparse's, not rclpy's.
    rclpy.init(args=[prog], signal_handler_options=SignalHandlerOptions.NO)


@contextlib.contextmanager
def _sigterm_raises() -> Iterator[None]:
    # Left as the caller set it; and outside the main thread, where signal.signal raises
    # ValueError (main() called from a thread failed so before it asked anything).
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL
    ):
        yield
        return

    def _raise(signum: int, frame: object) -> None:
        raise _Terminated

    signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def interruptible(prog: str, body: Callable[[], int]) -> int:
    """``body()``, where Ctrl-C ends it with one line and status 130 and SIGTERM (``timeout``,
    a CI runner) with 143, as a shell reports those signals, instead of a traceback."""
    try:
        with _sigterm_raises():
            return body()
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return 130
    except _Terminated:
        print(f'{prog}: terminated', file=sys.stderr)
        return 143


def node_name(name: str) -> str:
    """``name`` as a fully qualified node name (a leading ``/``)."""
    return name if name.startswith('/') else f'/{name}'


def bad_node_name(target: str) -> str | None:
    """Why the fully qualified ``target`` is no node name (the first line of rclpy's message,
    which goes on with a caret under the offending character), or None where it is one.

    Checked before any client is made: rclpy's ``InvalidServiceNameException`` would come as
    a traceback with exit status 1, which the tools use for a refusal by the node.
    """
    from rclpy.exceptions import NameValidationException
    from rclpy.validate_namespace import validate_namespace
    from rclpy.validate_node_name import validate_node_name

    namespace, _, base = target.rpartition('/')
    try:
        validate_namespace(namespace or '/')
        validate_node_name(base)
    except NameValidationException as error:
        return str(error).splitlines()[0].removesuffix(':')
    return None


def ask(node: Any, client: Any, request: Any, deadline: float) -> Any:
    """Send ``request`` until one copy is answered or ``deadline`` (monotonic s) passes.

    ``wait_for_service`` sees the request path only: a reply the node sends before it has
    discovered this client's reply reader is lost (a known race of DDS services, likelier in a
    domain where many participants come and go). So while nothing is answered the request is
    sent again every :data:`ATTEMPT_S` seconds, and the first answer to any copy counts.

    Returns:
        The answer, or None.
    """
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    futures: list[Any] = []
    next_send = time.monotonic()
    try:
        while (now := time.monotonic()) < deadline:
            done = [future for future in futures if future.done()]
            if done:
                return done[0].result()
            if now >= next_send:
                futures.append(client.call_async(request))
                next_send = now + ATTEMPT_S
            executor.spin_once(timeout_sec=min(0.05, max(deadline - now, 0.0)))
        done = [future for future in futures if future.done()]
        return done[0].result() if done else None
    finally:
        executor.remove_node(node)
        executor.shutdown()


def call(node: Any, srv_type: Any, service: str, request: Any, deadline: float) -> Any:
    """The answer of ``service`` to ``request`` (sent as :func:`ask` sends it), or None when
    the service or its answer does not come by ``deadline`` (monotonic s)."""
    client = node.create_client(srv_type, service)
    try:
        if not client.wait_for_service(timeout_sec=max(deadline - time.monotonic(), 0.0)):
            return None
        return ask(node, client, request, deadline)
    finally:
        node.destroy_client(client)


def _change_state(
    node: Any, client: Any, state_client: Any, request: Any, goal: str | None, deadline: float
) -> Any:
    """Send a transition once; its answer, or one made up from the node's state.

    A transition is not sent again as :func:`ask` would (the node refuses the copy, with an
    ``rcl_lifecycle`` warning in its log, whenever the first one takes longer than
    :data:`ATTEMPT_S`: a configure that loads a network does). The request itself reaches the
    node (``wait_for_service`` saw its reader); only the reply can be lost, so while none has
    come the state is asked every :data:`ATTEMPT_S` seconds, and the transition's goal state
    there counts as success: unless the node was in that state already before the transition
    was sent (``configure`` of an inactive node, which it refuses), when only its reply tells.

    Returns:
        The ``ChangeState`` answer (or one with ``success`` set from the state), or None.
    """
    from lifecycle_msgs.srv import ChangeState, GetState
    from rclpy.executors import SingleThreadedExecutor

    if goal is not None:
        before = ask(node, state_client, GetState.Request(),
                     min(deadline, time.monotonic() + ATTEMPT_S))
        if before is not None and before.current_state.label == goal:
            goal = None  # the goal state tells nothing: a lost refusal read as success
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    change = client.call_async(request)
    polls: list[Any] = []
    next_poll = time.monotonic() + ATTEMPT_S
    try:
        while (now := time.monotonic()) < deadline:
            if change.done():
                return change.result()
            for poll in polls:
                answer = poll.result() if poll.done() else None
                if answer is not None and goal is not None and (
                    answer.current_state.label == goal
                ):
                    return ChangeState.Response(success=True)
            if now >= next_poll:
                polls.append(state_client.call_async(GetState.Request()))
                next_poll = now + ATTEMPT_S
            executor.spin_once(timeout_sec=min(0.05, max(deadline - now, 0.0)))
        return change.result() if change.done() else None
    finally:
        executor.remove_node(node)
        executor.shutdown()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (130 / 143 after Ctrl-C / SIGTERM)."""
    args = _parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    return interruptible('cva-lifecycle', lambda: _main(args))


def _main(args: argparse.Namespace) -> int:
    if not args.timeout > 0:  # nan too (it waited no time and said "within nan s")
        print(f'cva-lifecycle: --timeout must be > 0 s; got {args.timeout:g}', file=sys.stderr)
        return EXIT_NO_ANSWER
    if args.command == 'set' and not args.transition.strip():
        # Sent, an empty label asks for transition id 0, which rclpy's managed nodes raise on
        # in their executor: the node ended, and this waited for an answer that never came.
        print(f"cva-lifecycle: TRANSITION must be a transition's label ({', '.join(GOALS)}); "
              f'got {args.transition!r}', file=sys.stderr)
        return EXIT_NO_ANSWER
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetAvailableTransitions, GetState
    import rclpy

    target = node_name(args.node)
    why = bad_node_name(target)
    if why is not None:
        print(f'cva-lifecycle: {args.node!r} is not a node name ({why})', file=sys.stderr)
        return EXIT_NO_ANSWER
    deadline = time.monotonic() + args.timeout
    init_rclpy('cva-lifecycle')
    try:
        node = rclpy.create_node(f'cva_lifecycle_{os.getpid()}')
        try:
            if args.command == 'get':
                service, srv_type, request = f'{target}/get_state', GetState, GetState.Request()
            elif args.command == 'list':
                service, srv_type = f'{target}/get_available_transitions', GetAvailableTransitions
                request = GetAvailableTransitions.Request()
            else:
                service, srv_type = f'{target}/change_state', ChangeState
                request = ChangeState.Request(transition=Transition(label=args.transition))
            client = node.create_client(srv_type, service)
            answer = None
            allowed: list[str] | None = None
            found = client.wait_for_service(timeout_sec=args.timeout)
            if found:
                if args.command == 'set':
                    state_client = node.create_client(GetState, f'{target}/get_state')
                    goal = GOALS.get(args.transition)
                    answer = _change_state(node, client, state_client, request, goal, deadline)
                    if answer is not None and not answer.success:
                        allowed = _allowed(node, target, deadline)
                else:
                    answer = ask(node, client, request, deadline)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    if answer is None and not found:
        print(f'cva-lifecycle: no answer from {service} within {args.timeout:g} s (is {target} '
              'running, a managed node, and in this ROS_DOMAIN_ID?)', file=sys.stderr)
        return EXIT_NO_ANSWER
    if answer is None:
        # The service is there: the node is busy (a transition that loads a network), not gone.
        busy = ('the transition may still be going on' if args.command == 'set'
                else 'it may be busy with a transition')
        print(f'cva-lifecycle: {service} is there but did not answer within {args.timeout:g} s '
              f'({busy}; `cva-lifecycle get {target}` tells its state, a longer --timeout '
              'waits for it)', file=sys.stderr)
        return EXIT_NO_ANSWER
    if args.command == 'get':
        print(f'{answer.current_state.label} [{answer.current_state.id}]')
        return 0
    if args.command == 'list':
        for item in answer.available_transitions:
            print(f'- {item.transition.label} [{item.transition.id}]\n'
                  f'\tStart: {item.start_state.label}\n\tGoal: {item.goal_state.label}')
        return 0
    if answer.success:
        print('Transitioning successful')
        return 0
    if allowed is None:
        hint = f'see its log; `cva-lifecycle list {target}` shows what its state allows'
    elif args.transition in allowed:
        hint = 'its state allows it, so the transition itself failed: see its log'
    else:
        hint = f'its state allows: {", ".join(allowed) or "no transition"}'
    print(f'Transitioning failed: {target} refused {args.transition!r} ({hint})', file=sys.stderr)
    return EXIT_REFUSED


def _allowed(node: Any, target: str, deadline: float) -> list[str] | None:
    """The labels of the transitions ``target``'s state allows (once each); None: no answer.

    Asked after a refusal, with at least a second to answer even if ``deadline`` has passed.
    """
    from lifecycle_msgs.srv import GetAvailableTransitions

    answer = call(
        node, GetAvailableTransitions, f'{target}/get_available_transitions',
        GetAvailableTransitions.Request(), max(deadline, time.monotonic() + 1.0),
    )
    if answer is None:
        return None
    labels = [item.transition.label for item in answer.available_transitions]
    return list(dict.fromkeys(labels))


if __name__ == '__main__':
    sys.exit(main())
