"""Message types of the FingerVision bus and their wire codec."""
from msgs.camera import CameraInfo, Image
from msgs.flow import Unanswered
from msgs.message import ArraySpec, Message, MessageError
from msgs.param import ParamSet, ParamState
from msgs.status import NodeStatus
from msgs.tactile import ContactSummary, DisplacementField, GraspStart, MarkerArray, SlipState
from msgs.wire import decode, decode_header, encode, known_types, message_type, register

for _cls in (Image, CameraInfo, MarkerArray, DisplacementField, ContactSummary, SlipState, GraspStart, NodeStatus,
             Unanswered, ParamSet, ParamState):
    register(_cls)

__all__ = [
    "ArraySpec", "CameraInfo", "ContactSummary", "DisplacementField", "GraspStart", "Image", "MarkerArray",
    "Message", "MessageError", "NodeStatus", "SlipState", "Unanswered", "decode", "decode_header", "encode",
    "known_types", "message_type", "register",
]
