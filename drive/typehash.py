"""RIHS01 type hashes (REP-2011) of the message definitions in ``drive.messages.MSG_DEFS``.

rosbag2 (Jazzy) records a topic's type hash in the MCAP channel's ``topic_type_hash`` metadata and in
``metadata.yaml`` (``type_description_hash``). The hash is ``RIHS01_`` + the SHA-256 of the JSON text
(``json.dumps`` with its default separators) of the type's description: ``type_description`` (its name and
fields) and ``referenced_type_descriptions`` (every nested type, sorted by name), where each field is its
name and ``type`` {``type_id``, ``capacity``, ``string_capacity``, ``nested_type_name``}; constants and
default values are not part of it. ``type_id``: the primitive's id (rosidl's type_description_interfaces
FieldType) or 1 for a nested type, plus 48 for a fixed array, 96 for a bounded and 144 for an unbounded
sequence. Checked against rosbags' Jazzy typestore (tests/test_ros_profile.py).
"""
from __future__ import annotations

import hashlib
import json
import re
from functools import lru_cache

from fieldlog.drive.messages import MSG_DEFS

NESTED_TYPE = 1
PRIMITIVE_IDS = {"int8": 2, "uint8": 3, "int16": 4, "uint16": 5, "int32": 6, "uint32": 7, "int64": 8,
                 "uint64": 9, "float32": 10, "float64": 11, "char": 13, "bool": 15, "byte": 16, "string": 17}
ARRAY, BOUNDED_SEQUENCE, UNBOUNDED_SEQUENCE = 48, 96, 144
_FIELD = re.compile(r"(?P<type>[A-Za-z0-9_/]+)(?:\[(?P<bound><=)?(?P<n>\d*)\])?\s+(?P<name>\w+)")


def _full_name(ref: str) -> str:
    pkg, name = ref.split("/")[0], ref.split("/")[-1]
    return f"{pkg}/msg/{name}"


def _fields(type_name: str) -> list[dict]:
    out = []
    for line in MSG_DEFS[type_name].splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or "=" in line:                      # comments, constants
            continue
        m = _FIELD.fullmatch(line)
        if m is None:
            raise ValueError(f"{type_name}: field {line!r} is not supported by the type hash")
        typ, n = m["type"], m["n"]
        nested = _full_name(typ) if "/" in typ else ""
        tid = NESTED_TYPE if nested else PRIMITIVE_IDS[typ]
        if "[" not in line:
            inc, capacity = 0, 0
        elif m["bound"]:
            inc, capacity = BOUNDED_SEQUENCE, int(n)
        elif n:
            inc, capacity = ARRAY, int(n)
        else:
            inc, capacity = UNBOUNDED_SEQUENCE, 0
        out.append({"name": m["name"], "type": {"type_id": tid + inc, "capacity": capacity, "string_capacity": 0,
                                                "nested_type_name": nested}})
    return out or [{"name": "structure_needs_at_least_one_member",
                    "type": {"type_id": PRIMITIVE_IDS["uint8"], "capacity": 0, "string_capacity": 0,
                             "nested_type_name": ""}}]


@lru_cache(maxsize=None)
def rihs01(type_name: str) -> str:
    """``RIHS01_<sha256 hex>`` of ``type_name`` (a key of MSG_DEFS, e.g. ``sensor_msgs/msg/Imu``).

    Parameters
    ----------
    type_name : a registered type

    Returns
    -------
    str : the type hash
    """
    structs: dict[str, dict] = {}

    def visit(t: str) -> None:
        if t in structs:
            return
        structs[t] = {"type_name": t, "fields": _fields(t)}
        for f in structs[t]["fields"]:
            if f["type"]["nested_type_name"]:
                visit(f["type"]["nested_type_name"])

    visit(type_name)
    desc = {"type_description": structs[type_name],
            "referenced_type_descriptions": [v for k, v in sorted(structs.items()) if k != type_name]}
    return "RIHS01_" + hashlib.sha256(json.dumps(desc).encode()).hexdigest()
