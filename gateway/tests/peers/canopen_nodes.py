#!/usr/bin/python3
"""CANopen nodes for hwgw's tests: Python canopen LocalNodes (an implementation we did not
write) on a SocketCAN interface, each over an EDS the test ships, with the little device
application a real IO module or drive runs around its object dictionary:

- power-on and NMT reset (node or communication): the communication objects
  (0x1000-0x1FFF) back to the EDS defaults, boot-up sent, pre-operational, the heartbeat
  from 0x1017;
- NMT start: the PDO configuration read from the node's own dictionary (canopen's PDO
  reader), RPDOs subscribed (each one received is written into the dictionary by
  canopen's PDO decoding), event-driven TPDOs sent once;
- a dictionary value set by the test: every TPDO carrying it is filled by canopen's PDO
  encoding and sent at once (event-driven) or at the next SYNC (synchronous).

JSON lines on stdin, one answer each:

  {"set": [ID, INDEX, SUB, VALUE]}      -> {"ok": true}
  {"get": [ID, INDEX, SUB]}             -> {"value": V, "data": "HEX"}
  {"pdo": [ID, "tpdo"|"rpdo", N]}       -> {"cob_id", "enabled", "trans_type", "mapped"}
  {"nmt": ID}                           -> {"state": "OPERATIONAL", ...}
  {"silence": ID}                       -> the node stops (no heartbeat, ignores frames)
  {"power_on": ID}                      -> the node boots again
  {"emcy": [ID, CODE, REGISTER]}        -> one emergency sent
  {"refuse": [ID, INDEX, SUB, CODE]}    -> SDO writes of that object aborted with CODE
  {"rpdos": ID}                         -> {"count": N}  RPDOs received while operational

Usage: canopen_nodes.py IFACE ID:EDS [ID:EDS ...]
"""
import json
import struct
import sys
import threading

import canopen
from canopen.sdo.exceptions import SdoAbortedError

lock = threading.RLock()
net = canopen.Network()
net.connect(interface="socketcan", channel=sys.argv[1])


class Device:
    def __init__(self, node_id, eds):
        self.id = node_id
        self.node = canopen.LocalNode(node_id, eds)
        self.alive = True
        self.refused = {}
        self.rpdos = 0
        self.subscribed = []
        net.add_node(self.node)
        self.node.add_write_callback(self.on_write)
        net.subscribe(0, self.on_nmt)
        net.subscribe(0x80, self.on_sync)
        self.power_on()

    def on_write(self, index, subindex, od, data):
        code = self.refused.get((index, subindex))
        if code is not None:
            raise SdoAbortedError(code)

    def power_on(self):
        with lock:
            if not self.alive:
                net.subscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
            self.alive = True
            self.node.nmt.stop_heartbeat()
            for index in [i for i in self.node.data_store if 0x1000 <= i <= 0x1FFF]:
                del self.node.data_store[index]
            self.unsubscribe()
            # Pre-operational before the boot-up frame goes out, as a device is: a master
            # answering the boot-up at once (writing 0x1017) finds it there.
            self.node.nmt.send_command(0x80)
            net.send_message(0x700 + self.id, [0])
            self.node.nmt.start_heartbeat(self.node.sdo[0x1017].raw)

    def silence(self):
        with lock:
            self.alive = False
            self.node.nmt.stop_heartbeat()
            self.unsubscribe()
            net.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)

    def unsubscribe(self):
        for cob_id, cb in self.subscribed:
            net.unsubscribe(cob_id, cb)
        self.subscribed = []

    def on_nmt(self, can_id, data, timestamp):
        command, node_id = struct.unpack_from("BB", data)
        if node_id not in (0, self.id) or not self.alive:
            return
        if command in (0x81, 0x82):
            # canopen's NmtSlave only takes the state; a device boots again.
            self.power_on()
        elif command == 0x01:
            self.started()

    def started(self):
        with lock:
            self.unsubscribe()
            self.node.rpdo.read()
            self.node.tpdo.read()
            for m in self.node.rpdo.map.values():
                if m.enabled:
                    if self.on_rpdo not in m.callbacks:
                        m.add_callback(self.on_rpdo)
                    net.subscribe(m.cob_id, m.on_message)
                    self.subscribed.append((m.cob_id, m.on_message))
            for m in self.node.tpdo.map.values():
                if m.enabled and (m.trans_type or 0) >= 254:
                    self.fill(m)
                    m.transmit()

    def on_rpdo(self, m):
        with lock:
            if not self.alive:
                return
            self.rpdos += 1
            for var in m.map:
                self.node.set_data(var.index, var.subindex, var.get_data())

    def fill(self, m):
        for var in m.map:
            try:
                data = self.node.get_data(var.index, var.subindex)
            except SdoAbortedError:
                # An input the EDS gives no default: 0 until the test sets it.
                data = bytes(len(var.od) // 8)
            var.set_data(data)

    def on_sync(self, can_id, data, timestamp):
        with lock:
            if not self.alive or self.node.nmt.state != "OPERATIONAL":
                return
            for m in self.node.tpdo.map.values():
                if m.enabled and m.trans_type is not None and m.trans_type <= 240:
                    self.fill(m)
                    m.transmit()

    def set(self, index, sub, value):
        with lock:
            self.node.sdo[index][sub].raw = value
            if not self.alive or self.node.nmt.state != "OPERATIONAL":
                return
            for m in self.node.tpdo.map.values():
                if not m.enabled or (m.trans_type or 0) < 254:
                    continue
                if any((v.index, v.subindex) == (index, sub) for v in m.map):
                    self.fill(m)
                    m.transmit()


devices = {}
for spec in sys.argv[2:]:
    node_id, eds = spec.split(":", 1)
    devices[int(node_id, 0)] = Device(int(node_id, 0), eds)
print(json.dumps({"ready": True}), flush=True)

for line in sys.stdin:
    req = json.loads(line)
    if "set" in req:
        i, index, sub, value = req["set"]
        devices[i].set(index, sub, value)
        answer = {"ok": True}
    elif "get" in req:
        i, index, sub = req["get"]
        with lock:
            d = devices[i]
            answer = {"value": d.node.sdo[index][sub].raw,
                      "data": d.node.get_data(index, sub).hex()}
    elif "pdo" in req:
        i, kind, n = req["pdo"]
        with lock:
            d = devices[i]
            m = (d.node.tpdo if kind == "tpdo" else d.node.rpdo).map[n]
            m.read()
            answer = {"cob_id": m.cob_id, "enabled": m.enabled, "trans_type": m.trans_type,
                      "mapped": [[v.index, v.subindex, v.length] for v in m.map]}
    elif "nmt" in req:
        d = devices[req["nmt"]]
        answer = {"state": d.node.nmt.state,
                  "heartbeat_ms": struct.unpack("<H", d.node.get_data(0x1017, 0))[0]}
    elif "silence" in req:
        devices[req["silence"]].silence()
        answer = {"ok": True}
    elif "power_on" in req:
        devices[req["power_on"]].power_on()
        answer = {"ok": True}
    elif "emcy" in req:
        i, code, register = req["emcy"]
        devices[i].node.emcy.send(code, register)
        answer = {"ok": True}
    elif "refuse" in req:
        i, index, sub, code = req["refuse"]
        devices[i].refused[(index, sub)] = code
        answer = {"ok": True}
    elif "rpdos" in req:
        answer = {"count": devices[req["rpdos"]].rpdos}
    else:
        answer = {"error": "unknown request %r" % (req,)}
    print(json.dumps(answer), flush=True)
