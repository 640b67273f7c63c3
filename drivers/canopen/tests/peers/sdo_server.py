#!/usr/bin/python3
"""Python canopen's SDO server (an implementation we did not write) for hwgw's SDO client
tests, with no bus: a canopen.LocalNode over an EDS whose SDO server is handed each
request frame and whose responses are collected. JSON lines on stdin, one answer each:

  {"request": "HEX"}          -> {"responses": ["HEX", ...]}  (frames sent on 0x580+node)
  {"get": [INDEX, SUB]}       -> {"data": "HEX"}              (the node's stored bytes)
  {"pdo": "tpdo"|"rpdo", "number": N}
      -> {"cob_id": C, "enabled": B, "trans_type": T, "event_timer": E,
          "mapped": [[INDEX, SUB, BITS], ...]}   (canopen's own reading of the PDO's
                                                  configuration, through its SDO server)

Usage: sdo_server.py EDS NODE_ID
"""
import json
import sys

import canopen


class Bus:
    """Stands in for canopen.Network: what the server sends is kept."""

    def __init__(self):
        self.sent = []

    def send_message(self, can_id, data, remote=False):
        self.sent.append((can_id, bytes(data).hex()))

    def subscribe(self, can_id, callback):
        pass

    def unsubscribe(self, can_id, callback=None):
        pass


node_id = int(sys.argv[2], 0)
node = canopen.LocalNode(node_id, sys.argv[1])
bus = Bus()
node.sdo.network = bus
node.tpdo.network = bus
node.rpdo.network = bus
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    req = json.loads(line)
    if "request" in req:
        bus.sent.clear()
        node.sdo.on_request(0x600 + node_id, bytes.fromhex(req["request"]), 0)
        assert all(c == 0x580 + node_id for c, _ in bus.sent), bus.sent
        print(json.dumps({"responses": [d for _, d in bus.sent]}), flush=True)
    elif "pdo" in req:
        maps = node.tpdo if req["pdo"] == "tpdo" else node.rpdo
        m = maps[req["number"]]
        m.read()
        print(json.dumps({
            "cob_id": m.cob_id,
            "enabled": m.enabled,
            "trans_type": m.trans_type,
            "event_timer": m.event_timer,
            "mapped": [[v.index, v.subindex, v.length] for v in m.map],
        }), flush=True)
    elif "get" in req:
        index, sub = req["get"]
        print(json.dumps({"data": node.get_data(index, sub).hex()}), flush=True)
