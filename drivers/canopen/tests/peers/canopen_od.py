#!/usr/bin/python3
"""Python canopen's reading of an EDS (an implementation we did not write), as JSON, for
hwgw's EDS tests: canopen.import_od(FILE, NODE_ID), every object and sub-index with its
name, data type, access type, PDO mapping, default (the node id added), limits.

Usage: canopen_od.py FILE NODE_ID
"""
import json
import sys

import canopen
from canopen import objectdictionary as odm


def value(v):
    if isinstance(v, (bytes, bytearray)):
        return {"bytes": bytes(v).hex()}
    return v


def variable(v):
    return {
        "sub": v.subindex,
        "name": v.name,
        "data_type": v.data_type,
        "access": v.access_type,
        "pdo_mappable": bool(v.pdo_mappable),
        "default": value(v.default),
        "relative": bool(v.relative),
        "min": v.min,
        "max": v.max,
    }


od = canopen.import_od(sys.argv[1], int(sys.argv[2], 0))
objects = []
for index in sorted(od.indices):
    obj = od[index]
    if isinstance(obj, odm.ODVariable):
        objects.append({"index": index, "name": obj.name, "kind": "variable", "subs": [variable(obj)]})
    else:
        kind = "array" if isinstance(obj, odm.ODArray) else "record"
        subs = [variable(obj.subindices[s]) for s in sorted(obj.subindices)]
        objects.append({"index": index, "name": obj.name, "kind": kind, "subs": subs})
print(json.dumps({"objects": objects}))
