"""The CNC controller's own account, as the daemon's OPC UA client received it (``[controller]``).

One :class:`ControllerMessage` per batch of data changes the server published (its publishing interval), and one
at each connection and loss; recorded on the MCAP channel ``/ballbar/controller``.  Every value carries the
server's source timestamp and that time on the daemon's monotonic clock, so that the controller's data and the
bar's samples (``t_host``) share one time axis.
"""

from typing import Annotated, Literal, NotRequired, TypedDict

from .envelope import MachineId, THost, TWall, Version
from .fields import doc

#: What a node's value can be: a number, a string, a flag, or an array of them (ActGFunctions, ActProgramBlock).
Value = str | float | bool | list[str | float | bool] | None


class ControllerValue(TypedDict):
    """one node's new value"""

    name: Annotated[str, doc("the node map's name: program, override, feed, g_functions, block, act_pos.<axis>, "
                             "cmd_pos.<axis>, or a name the configuration added")]
    value: Annotated[Value, doc("the value as the server gave it (override in %, feed in the server's unit, "
                                "positions in mm)", null="no value (status not good)")]
    t_source: Annotated[str | None, doc("the server's source timestamp, ISO 8601 UTC", null="the server gave none")]
    t_host: Annotated[float | None, doc("that time on the daemon's monotonic clock (t_source + the stated clock "
                                        "offset; else the time it was received)", "s")]
    status: NotRequired[Annotated[str, doc("the value's OPC UA status when not Good (e.g. BadNodeIdUnknown)")]]


class ControllerMessage(TypedDict):
    """ballbar.Controller: the CNC controller's data over OPC UA ([controller]); MCAP /ballbar/controller."""

    schema_version: Version
    kind: Annotated[Literal["controller"], doc("what the payload is")]
    machine_id: MachineId
    t_wall: TWall
    t_host: THost
    endpoint: Annotated[str, doc("the server's endpoint (opc.tcp://...)")]
    state: Annotated[Literal["connected", "data", "lost"], doc(
        "connected: the session is up and the node map resolved (missing names what the server lacks); data: "
        "values changed; lost: the connection ended (detail says why)")]
    values: Annotated[list[ControllerValue], doc("the values that changed, in the server's order (on connected: "
                                                 "each node's value then)")]
    clock_offset_s: Annotated[float | None, doc(
        "the daemon's wall clock minus the server's, estimated as the smallest arrival minus source timestamp "
        "seen (it includes the shortest transport and publishing delay)", "s", null="not known yet")]
    missing: NotRequired[Annotated[list[str], doc("on connected: the map's names the server lacks")]]
    repeated: NotRequired[Annotated[bool, doc("at the head of an MCAP file: the last value of each node before it "
                                              "(state data), so that a file alone says what the controller ran")]]
    detail: NotRequired[Annotated[str, doc("on lost: why, in words")]]
