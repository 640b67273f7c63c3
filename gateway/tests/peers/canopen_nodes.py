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
  encoding and sent at once (event-driven) or at the next SYNC (synchronous);
- a CiA 402 drive (`ID:EDS:402`): each controlword received moves its statusword through
  the CiA 402 state diagram (shutdown, switch on, enable operation, disable voltage,
  quick stop, fault reset on a rising edge of bit 7); its velocity actual (0x606C) follows
  the target velocity (0x60FF) while operation is enabled, else 0.

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
  {"fault": ID}                         -> the drive goes to Fault

Usage: canopen_nodes.py IFACE ID:EDS[:402] [ID:EDS[:402] ...]
"""
import json
import struct
import sys
import threading

import canopen
from canopen.sdo.exceptions import SdoAbortedError

lock = threading.RLock()


def var(node, index, sub):
    """The dictionary entry: a sub-index of a record or array, or a plain variable."""
    obj = node.sdo[index]
    try:
        return obj[sub]
    except TypeError:
        return obj
net = canopen.Network()
net.connect(interface="socketcan", channel=sys.argv[1])


# CiA 402: statusword per state, and the transitions a controlword makes.
SW = {"disabled": 0x40, "ready": 0x21, "on": 0x23, "enabled": 0x27, "quick": 0x07, "fault": 0x08}


def cia402(state, cw, last):
    if state == "fault":
        return "disabled" if cw & 0x80 and not last & 0x80 else "fault"
    c = cw & 0x8F
    if c & 0x02 == 0:  # disable voltage
        return "disabled"
    if c & 0x04 == 0:  # quick stop
        return "quick" if state == "enabled" else "disabled"
    if c & 0x0F == 0x06:  # shutdown
        return "ready" if state in ("disabled", "ready", "on", "enabled") else state
    if c & 0x0F == 0x07:  # switch on
        return {"ready": "on", "on": "on", "enabled": "on"}.get(state, state)
    if c & 0x0F == 0x0F:  # enable operation
        return {"ready": "enabled", "on": "enabled", "enabled": "enabled"}.get(state, state)
    return state


class Device:
    def __init__(self, node_id, eds, profile=None):
        self.drive = profile == "402"
        self.state = "disabled"
        self.last_cw = 0
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
            if self.drive:
                self.state, self.last_cw = "disabled", 0
                self.node.set_data(0x6041, 0, struct.pack("<H", SW["disabled"]))
                self.node.set_data(0x606C, 0, struct.pack("<i", 0))
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
            # A node takes PDOs only while operational.
            if not self.alive or self.node.nmt.state != "OPERATIONAL":
                return
            self.rpdos += 1
            for var in m.map:
                self.node.set_data(var.index, var.subindex, var.get_data())
            if self.drive:
                self.drive_step()

    def drive_step(self):
        cw = struct.unpack("<H", self.node.get_data(0x6040, 0))[0]
        self.state = cia402(self.state, cw, self.last_cw)
        self.last_cw = cw
        target = struct.unpack("<i", self.node.get_data(0x60FF, 0))[0]
        self.publish({0x6041: struct.pack("<H", SW[self.state]),
                      0x606C: struct.pack("<i", target if self.state == "enabled" else 0)})

    def publish(self, values):
        """Writes `values` (index -> bytes, sub 0) and sends the event TPDOs carrying
        any that changed."""
        changed = set()
        for index, data in values.items():
            try:
                old = self.node.get_data(index, 0)
            except SdoAbortedError:
                old = None
            if old != data:
                self.node.set_data(index, 0, data)
                changed.add(index)
        if not changed or self.node.nmt.state != "OPERATIONAL":
            return
        for m in self.node.tpdo.map.values():
            if m.enabled and (m.trans_type or 0) >= 254 and any(
                    (v.index, v.subindex) in [(i, 0) for i in changed] for v in m.map):
                self.fill(m)
                m.transmit()

    def fault(self):
        with lock:
            self.state = "fault"
            self.publish({0x6041: struct.pack("<H", SW["fault"]),
                          0x606C: struct.pack("<i", 0)})

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
            var(self.node, index, sub).raw = value
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
    node_id, rest = spec.split(":", 1)
    eds, _, profile = rest.partition(":")
    devices[int(node_id, 0)] = Device(int(node_id, 0), eds, profile or None)
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
            answer = {"value": var(d.node, index, sub).raw,
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
    elif "fault" in req:
        devices[req["fault"]].fault()
        answer = {"ok": True}
    elif "rpdos" in req:
        answer = {"count": devices[req["rpdos"]].rpdos}
    else:
        answer = {"error": "unknown request %r" % (req,)}
    print(json.dumps(answer), flush=True)
