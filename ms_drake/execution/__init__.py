"""Action execution: the ActionExecutor system and its two fidelities (primitive: the floating
gripper's evaluated grasp primitive; full: IK + ruckig through the station's drivers on any robot)."""

from ms_drake.execution.backends import (  # noqa: F401
    FIDELITIES,
    GRASP_OUTCOMES,
    LIFT_THRESHOLD,
    PRIMITIVE_PUSH_TIME_STEP,
    FullBackend,
    PrimitiveBackend,
    grasp_tool_pose,
    tcp_offset_of,
)
from ms_drake.execution.carrier import CarrierError, ObjectCarrier  # noqa: F401
from ms_drake.execution.executor import (  # noqa: F401
    NO_OUTCOME,
    ActionExecutor,
    SimulationBlewUp,
    ExecutionError,
    ExecutorStatus,
    Motion,
    connect_executor,
    remove_objects,
)
