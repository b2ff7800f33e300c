"""What the gateway's action servers (``~/move``, ``~/program_download``) share."""

from typing import Callable, Dict

from rclpy.action import CancelResponse


def cancel_goal(cancels: Dict[bytes, Callable[[], None]], goal_handle) -> CancelResponse:
    """Run the cancel kept for ``goal_handle``'s goal id; reject a goal that has none (ended)."""
    cancel = cancels.get(bytes(goal_handle.goal_id.uuid))
    if cancel is None:
        return CancelResponse.REJECT
    cancel()
    return CancelResponse.ACCEPT
