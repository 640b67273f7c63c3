#!/usr/bin/env python3
"""An independent Sparkplug B host application, a peer for hwgw's MQTT tests.

It uses paho-mqtt and mqtt-spb-wrapper's protobuf module (not hwgw's code), so what it
prints is what another implementation makes of hwgw's messages.

    sparkplug_host.py --broker 127.0.0.1:PORT --group G --node N --host-id H
                      [--tls-ca ca.pem --tls-cert c.pem --tls-key c.key] [--count]

It keeps a persistent session (client id `sparkplug-host-H`, clean session false), so a
broker with `persistence true` delivers what was queued for it, an edge node's NDEATH
will included, when it reconnects after a restart. On every connection it subscribes
QoS 1 to `spBv1.0/G/#` and then publishes its STATE (`spBv1.0/STATE/H`, retained, QoS 1,
`{"online": true, "timestamp": MS}`); its will is the same with `"online": false`.

One JSON object a line on stdout:
  {"event": "ready"}                 first connection, subscription acknowledged
  {"event": "disconnected"} / {"event": "connected"} (the latter once resubscribed)
  {"event": "message", "type": "NBIRTH", "topic": ..., "device": D or null,
   "seq": int or null, "timestamp": int or null,
   "metrics": [{"name", "alias", "datatype", "value", "properties": {key: value}}]}
  {"event": "done", "cmd": ...}      a command was published
  {"event": "error", "message": ...} anything it could not decode or do, and a failed
                                     connection attempt (once an outage; it keeps trying)
A metric given by alias alone gets its name (and datatype) from the births seen. Values:
signed integers decoded from their two's complement, floats as JSON numbers (repr, so they
round-trip; NaN and infinities as the strings "NaN", "Infinity", "-Infinity"), bytes as
hex, null when is_null or of a kind not decoded (DataSet, Template).

With --count (for the benchmark) it decodes every message all the same, but prints instead
of each one a line a second: {"event": "count", "messages": N, "metrics": N, "bytes": N,
"seconds": S}, the totals since the first message.

Commands, one JSON object a line on stdin:
  {"cmd": "rebirth"}                           NCMD Node Control/Rebirth = true
  {"cmd": "ncmd", "metrics": [...]}            NCMD with these metrics
  {"cmd": "dcmd", "device": D, "metrics": [{"name", "datatype", "value"}, ...]}
  {"cmd": "state", "online": true|false}       STATE, retained, QoS 1
  {"cmd": "quit"}                              STATE offline, disconnect, exit
NCMD and DCMD go with QoS 0, not retained, as Sparkplug says. End of input quits too
(without the "done").
"""
import argparse
import json
import math
import sys
import threading
import time

import paho.mqtt.client as mqtt
from mqtt_spb_wrapper.spb_protobuf.sparkplug_b_pb2 import Payload

TYPES = {"NBIRTH", "NDATA", "NDEATH", "NCMD", "DBIRTH", "DDATA", "DDEATH", "DCMD"}
SIGNED_BITS = {1: 8, 2: 16, 3: 32, 4: 64}  # Int8..Int64
INT_FIELD = {1, 2, 3, 5, 6, 7}  # int_value (uint32)
LONG_FIELD = {4, 8, 13}  # long_value (uint64): Int64, UInt64, DateTime
_out = threading.Lock()


def emit(**event):
    with _out:
        sys.stdout.write(json.dumps(event) + "\n")
        sys.stdout.flush()


def now_ms():
    return int(time.time() * 1000)


def decode(raw, datatype):
    """A metric's or property's value as JSON: `raw` is the oneof field set."""
    if isinstance(raw, bool) or isinstance(raw, str):
        return raw
    if isinstance(raw, int):
        bits = SIGNED_BITS.get(datatype)
        if bits:
            raw &= (1 << bits) - 1
            return raw - (1 << bits) if raw >> (bits - 1) else raw
        return raw
    if isinstance(raw, float):
        if math.isnan(raw):
            return "NaN"
        return raw if math.isfinite(raw) else ("Infinity" if raw > 0 else "-Infinity")
    if isinstance(raw, bytes):
        return raw.hex()
    return None


class Client(mqtt.Client):
    """paho 1.6's loop thread ends on an exception it does not expect (an SSL alert, as a
    broker refusing the client's certificate sends); this one reports it and goes on."""

    on_loop_error = None

    def _thread_main(self):
        while True:
            try:
                return self.loop_forever(retry_first_connection=True)
            except Exception as e:  # noqa: BLE001
                self.on_loop_error(e)
                time.sleep(0.5)
                if self._thread_terminate or self._state == mqtt.mqtt_cs_disconnecting:
                    return None
                try:
                    self.reconnect()
                except Exception:  # noqa: BLE001 - loop_forever retries
                    pass


def property_set(ps):
    out = {}
    for key, pv in zip(ps.keys, ps.values):
        which = pv.WhichOneof("value")
        if pv.is_null or which is None:
            out[key] = None
        elif which == "propertyset_value":
            out[key] = property_set(pv.propertyset_value)
        elif which == "propertysets_value":
            out[key] = [property_set(p) for p in pv.propertysets_value.propertyset]
        else:
            out[key] = decode(getattr(pv, which), pv.type)
    return out


class Host:
    def __init__(self, args):
        self.a = args
        self.prefix = f"spBv1.0/{args.group}/"
        self.state_topic = f"spBv1.0/STATE/{args.host_id}"
        self.births = {}  # (node, device, alias) -> (name, datatype)
        self.types = {}  # (node, device, name) -> datatype
        self.ready = self.connected = self.failing = self.quitting = False
        self.sub_mid = None
        self.counted = None
        c = self.c = Client(client_id=f"sparkplug-host-{args.host_id}", clean_session=False)
        if args.tls_ca:
            c.tls_set(ca_certs=args.tls_ca, certfile=args.tls_cert, keyfile=args.tls_key)
        c.reconnect_delay_set(min_delay=0.1, max_delay=1)
        c.on_connect, c.on_disconnect = self.on_connect, self.on_disconnect
        c.on_connect_fail = lambda c, userdata: self.fail("cannot connect (retrying)")
        c.on_loop_error = self.on_loop_error
        c.on_subscribe, c.on_message = self.on_subscribe, self.on_message
        self.set_will()

    def state_payload(self, online):
        return json.dumps({"online": online, "timestamp": self.stamp})

    def set_will(self):
        """The will of the next connection; its STATE birth carries the same timestamp."""
        self.stamp = now_ms()
        self.c.will_set(self.state_topic, self.state_payload(False), qos=1, retain=True)

    def run(self):
        host, port = self.a.broker.rsplit(":", 1)
        self.c.connect_async(host, int(port), keepalive=10)
        self.c.loop_start()

    def fail(self, why):
        if not self.failing:  # once an outage, not once a retry
            emit(event="error", message=f"{self.a.broker}: {why}")
        self.failing = True

    def on_loop_error(self, e):
        self.fail(f"{type(e).__name__}: {e} (retrying)")
        if self.connected:
            self.on_disconnect(self.c, None, 1)

    def on_connect(self, c, userdata, flags, rc):
        if rc != 0:
            self.fail(f"CONNACK refused: {mqtt.connack_string(rc)} (retrying)")
            return
        self.failing, self.connected = False, True
        self.sub_mid = c.subscribe(self.prefix + "#", qos=1)[1]

    def on_subscribe(self, c, userdata, mid, granted_qos):
        if mid != self.sub_mid:
            return
        if granted_qos[0] > 2:
            emit(event="error", message=f"subscription refused: {granted_qos}")
        c.publish(self.state_topic, self.state_payload(True), qos=1, retain=True)
        emit(event="connected" if self.ready else "ready")
        self.ready = True

    def on_disconnect(self, c, userdata, rc):
        self.set_will()
        if self.connected and not self.quitting:
            emit(event="disconnected")
        self.connected = False

    def on_message(self, c, userdata, msg):
        try:
            event = self.message(msg.topic, msg.payload)
            if self.a.count:
                self.tally(len(event["metrics"]), len(msg.payload))
                return
            emit(**event)
        except Exception as e:  # noqa: BLE001 - a peer reports, never crashes
            emit(event="error", message=f"{msg.topic}: {type(e).__name__}: {e}")

    def tally(self, metrics, size):
        now = time.monotonic()
        if self.counted is None:
            self.counted = {"messages": 0, "metrics": 0, "bytes": 0, "first": now, "shown": now}
        t = self.counted
        t["messages"] += 1
        t["metrics"] += metrics
        t["bytes"] += size
        if now - t["shown"] >= 1.0:
            t["shown"] = now
            emit(event="count", messages=t["messages"], metrics=t["metrics"], bytes=t["bytes"],
                 seconds=now - t["first"])

    def message(self, topic, data):
        parts = topic.split("/")
        if len(parts) not in (4, 5) or parts[2] not in TYPES:
            raise ValueError("not a Sparkplug B edge node topic")
        kind, node = parts[2], parts[3]
        device = parts[4] if len(parts) == 5 else None
        p = Payload.FromString(data)
        if kind == "NBIRTH":
            self.births = {k: v for k, v in self.births.items() if k[0] != node}
            self.types = {k: v for k, v in self.types.items() if k[0] != node}
        metrics = []
        for m in p.metrics:
            alias = m.alias if m.HasField("alias") else None
            name = m.name if m.HasField("name") else None
            datatype = m.datatype if m.HasField("datatype") else None
            if name is None and alias is not None:
                name, known = self.births.get((node, device, alias), (None, None))
                datatype = known if datatype is None else datatype
            if datatype is None and name is not None:
                datatype = self.types.get((node, device, name))
            if kind in ("NBIRTH", "DBIRTH") and name is not None:
                self.types[(node, device, name)] = datatype
                if alias is not None:
                    self.births[(node, device, alias)] = (name, datatype)
            which = m.WhichOneof("value")
            value = None if m.is_null or which is None else decode(getattr(m, which), datatype)
            props = property_set(m.properties) if m.HasField("properties") else {}
            metrics.append({"name": name, "alias": alias, "datatype": datatype,
                            "value": value, "properties": props})
        return {"event": "message", "type": kind, "topic": topic, "device": device,
                "seq": p.seq if p.HasField("seq") else None,
                "timestamp": p.timestamp if p.HasField("timestamp") else None,
                "metrics": metrics}

    def publish(self, topic, payload, qos, retain=False, timeout=30.0):
        """Publishes and waits for it to be sent (QoS 0) or acknowledged (QoS 1)."""
        info = self.c.publish(topic, payload, qos=qos, retain=retain)
        # Not info.wait_for_publish(): it raises when the client is between connections,
        # though the message is queued and goes out on reconnection (QoS 1).
        deadline = time.monotonic() + timeout
        with info._condition:
            while not info._published:
                if not info._condition.wait(deadline - time.monotonic()):
                    raise TimeoutError(f"{topic} not published within {timeout} s")

    def command(self, kind, metrics, device=None):
        p = Payload()
        p.timestamp = now_ms()
        for spec in metrics:
            m = p.metrics.add()
            m.name, m.datatype, m.timestamp = spec["name"], int(spec["datatype"]), p.timestamp
            v, dt = spec.get("value"), m.datatype
            if v is None:
                m.is_null = True
            elif dt in INT_FIELD:
                m.int_value = int(v) & 0xFFFFFFFF
            elif dt in LONG_FIELD:
                m.long_value = int(v) & 0xFFFFFFFFFFFFFFFF
            elif dt == 9:
                m.float_value = float(v)
            elif dt == 10:
                m.double_value = float(v)
            elif dt == 11:
                m.boolean_value = bool(v)
            elif dt in (12, 14):
                m.string_value = str(v)
            else:
                raise ValueError(f"datatype {dt} not supported in commands")
        suffix = f"/{device}" if device is not None else ""
        self.publish(f"{self.prefix}{kind}/{self.a.node}{suffix}", p.SerializeToString(), qos=0)

    def goodbye(self):
        """STATE offline, as a host that stops on purpose publishes, then disconnects."""
        if self.quitting:
            return
        self.quitting = True
        try:
            self.publish(self.state_topic, self.state_payload(False), qos=1, retain=True, timeout=2.0)
        except Exception as e:  # noqa: BLE001 - quits all the same
            emit(event="error", message=f"quit: {type(e).__name__}: {e}")
        try:
            self.c.disconnect()
            time.sleep(0.2)  # for the DISCONNECT to go out; the loop thread is a daemon
        except Exception:  # noqa: BLE001 - exiting anyway
            pass

    def handle(self, line):
        req = json.loads(line)
        cmd = req["cmd"]
        if cmd == "rebirth":
            self.command("NCMD", [{"name": "Node Control/Rebirth", "datatype": 11, "value": True}])
        elif cmd == "ncmd":
            self.command("NCMD", req["metrics"])
        elif cmd == "dcmd":
            self.command("DCMD", req["metrics"], device=req["device"])
        elif cmd == "state":
            self.publish(self.state_topic, self.state_payload(bool(req["online"])), qos=1, retain=True)
        elif cmd == "quit":
            self.goodbye()
        else:
            raise ValueError(f"unknown command {cmd!r}")
        emit(event="done", cmd=cmd)
        return cmd != "quit"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--broker", required=True, help="HOST:PORT")
    ap.add_argument("--group", required=True)
    ap.add_argument("--node", required=True)
    ap.add_argument("--host-id", required=True)
    ap.add_argument("--tls-ca")
    ap.add_argument("--tls-cert")
    ap.add_argument("--tls-key")
    ap.add_argument("--count", action="store_true", help="print counts a second, not messages")
    host = Host(ap.parse_args())
    host.run()
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            if not host.handle(line):
                break
        except Exception as e:  # noqa: BLE001 - a peer reports, never crashes
            emit(event="error", message=f"{line.strip()}: {type(e).__name__}: {e}")
    host.goodbye()


if __name__ == "__main__":
    main()
