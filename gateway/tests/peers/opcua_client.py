#!/usr/bin/env python3
"""An independent OPC UA client for hwgw's tests: Python asyncua (FreeOpcUa), driven by
JSON lines.

    opcua_client.py '{"url": "opc.tcp://127.0.0.1:4840/", ...}'

The argument says how to connect: `url`; optionally `policy` ("Basic256Sha256",
"Aes128Sha256RsaOaep"), `mode` ("Sign", "SignAndEncrypt"), `cert` and `key` (the client's
certificate, DER, and key, PEM), `app_uri` (the URI in the certificate), `user` and
`password`. It prints one JSON line, {"connected": true} or {"error": "..."}, then takes
one JSON command a line on stdin and answers each with one JSON line:

- {"cmd": "browse"}: every variable under Objects/hwgw: node id, browse path, data type,
  value, status, and an analog one's EURange and unit.
- {"cmd": "read", "ids": [...]}: each value ({"value", "status", "source_ts", "server_ts"}).
- {"cmd": "write", "id": ..., "type": "Double"|"Boolean"|..., "value": ...}: the status.
- {"cmd": "call", "object": ..., "method": ..., "args": [[type, value], ...]}: the outputs
  or the status.
- {"cmd": "subscribe", "ids": [...], "interval": ms, "deadband": {"type": "absolute"|
  "percent", "value": x}, "queue": n}: statuses of the monitored items.
- {"cmd": "notifications", "count": n, "timeout": s}: waits until n data changes have come
  (or the timeout), returns them all ({"id", "value", "status"}) and forgets them.
- {"cmd": "flood", "sessions": n, "url": ...}: opens n more sessions (20 at a time) and
  keeps them open, never closed: how many opened, and the statuses of those refused.
- {"cmd": "many_items", "id": ..., "count": n, "chunk": k, "interval": ms}: one
  subscription with n monitored items of `id`, created k a request: the count of each
  status.
- {"cmd": "close"}: closes the session and ends.

Floats travel as JSON numbers written by Python's repr: they round-trip exactly.
"""

import asyncio
import json
import sys

from asyncua import Client, ua
from asyncua.crypto import security_policies


def status_name(code):
    try:
        return ua.StatusCode(code.value if hasattr(code, "value") else code).name
    except Exception:  # noqa: BLE001 - an unknown code is shown as its number
        return str(code)


def plain(v):
    if isinstance(v, (bool, int, float, str)) or v is None:
        return v
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    return str(v)


KEEP = []


async def flood(url, n):
    opened, refused = 0, {}

    async def one():
        nonlocal opened
        client = Client(url, timeout=30)
        try:
            await client.connect()
            opened += 1
            KEEP.append(client)
        except ua.UaStatusCodeError as e:
            name = status_name(e.code)
            refused[name] = refused.get(name, 0) + 1
        except Exception as e:  # noqa: BLE001 - counted by kind
            name = type(e).__name__
            refused[name] = refused.get(name, 0) + 1

    for i in range(0, n, 20):
        await asyncio.gather(*(one() for _ in range(min(20, n - i))))
    return {"opened": opened, "refused": refused}


class Handler:
    def __init__(self):
        self.changes = []
        self.event = asyncio.Event()

    def datachange_notification(self, node, val, data):
        dv = data.monitored_item.Value
        self.changes.append(
            {
                "id": node.nodeid.Identifier,
                "value": plain(val),
                "status": status_name(dv.StatusCode),
            }
        )
        self.event.set()


async def browse(client, ns):
    out = []
    root = await client.nodes.objects.get_child([f"{ns}:hwgw"])

    async def walk(node, path):
        for child in await node.get_children():
            name = (await child.read_browse_name()).Name
            cls = await child.read_node_class()
            here = path + [name]
            if cls == ua.NodeClass.Variable and child.nodeid.NamespaceIndex == ns:
                entry = {"id": child.nodeid.Identifier, "path": "/".join(here)}
                dv = await child.read_data_value(raise_on_bad_status=False)
                entry["value"] = plain(dv.Value.Value)
                entry["status"] = status_name(dv.StatusCode)
                dt = await child.read_data_type()
                entry["type"] = (await client.get_node(dt).read_browse_name()).Name
                for prop in await child.get_properties():
                    pname = (await prop.read_browse_name()).Name
                    if pname == "EURange":
                        r = await prop.read_value()
                        entry["range"] = [r.Low, r.High]
                    elif pname == "EngineeringUnits":
                        entry["unit"] = (await prop.read_value()).DisplayName.Text
                out.append(entry)
            elif cls == ua.NodeClass.Object and path[:1] != ["Components"]:
                await walk(child, here)

    await walk(root, [])
    return out


async def run(conf):
    client = Client(conf["url"], timeout=30)
    client.application_uri = conf.get("app_uri", "urn:hwgw:test-client")
    client.session_timeout = conf.get("session_timeout_ms", 30000)
    if "policy" in conf:
        policy = getattr(security_policies, "SecurityPolicy" + conf["policy"])
        mode = getattr(ua.MessageSecurityMode, conf.get("mode", "SignAndEncrypt"))
        await client.set_security(policy, certificate=conf["cert"], private_key=conf["key"], mode=mode)
    if "user" in conf:
        client.set_user(conf["user"])
        client.set_password(conf.get("password", ""))
    try:
        await client.connect()
    except Exception as e:  # noqa: BLE001 - the refusal is the answer
        print(json.dumps({"error": f"{type(e).__name__}: {e}"}), flush=True)
        return
    ns = await client.get_namespace_index("urn:hwgw:io")
    print(json.dumps({"connected": True, "ns": ns}), flush=True)
    handler = Handler()
    sub = None
    loop = asyncio.get_running_loop()
    node = lambda i: client.get_node(ua.NodeId(i, ns))  # noqa: E731
    while True:
        line = await loop.run_in_executor(None, sys.stdin.readline)
        if not line:
            break
        c = json.loads(line)
        try:
            answer = await command(client, ns, node, c, handler)
            if c["cmd"] == "subscribe":
                sub, answer = answer
            if c["cmd"] == "close":
                await client.disconnect()
                print(json.dumps({"closed": True}), flush=True)
                return
        except ua.UaStatusCodeError as e:
            answer = {"status": status_name(e.code)}
        except Exception as e:  # noqa: BLE001 - reported to the test
            answer = {"error": f"{type(e).__name__}: {e}"}
        print(json.dumps(answer), flush=True)
    del sub


async def command(client, ns, node, c, handler):
    cmd = c["cmd"]
    if cmd == "browse":
        return {"variables": await browse(client, ns)}
    if cmd == "read":
        out = []
        for i in c["ids"]:
            dv = await node(i).read_data_value(raise_on_bad_status=False)
            out.append(
                {
                    "value": plain(dv.Value.Value) if dv.Value is not None else None,
                    "status": status_name(dv.StatusCode),
                    "source_ts": str(dv.SourceTimestamp),
                }
            )
        return {"values": out}
    if cmd == "write":
        vt = getattr(ua.VariantType, c["type"])
        await node(c["id"]).write_value(ua.DataValue(ua.Variant(c["value"], vt)))
        return {"status": "Good"}
    if cmd == "call":
        args = [ua.Variant(v, getattr(ua.VariantType, t)) for t, v in c["args"]]
        out = await node(c["object"]).call_method(ua.NodeId(c["method"], ns), *args)
        return {"status": "Good", "outputs": plain(out)}
    if cmd == "subscribe":
        sub = await client.create_subscription(c.get("interval", 100), handler)
        filt = None
        if "deadband" in c:
            filt = ua.DataChangeFilter()
            filt.Trigger = ua.DataChangeTrigger.StatusValue
            kind = c["deadband"]["type"]
            filt.DeadbandType = 1 if kind == "absolute" else 2
            filt.DeadbandValue = float(c["deadband"]["value"])
        nodes = [node(i) for i in c["ids"]]
        handles = await sub._subscribe(
            nodes,
            ua.AttributeIds.Value,
            mfilter=filt,
            queuesize=c.get("queue", 0),
            sampling_interval=c.get("interval", 100),
        )
        bad = [status_name(h.value) if isinstance(h, ua.StatusCode) else "Good" for h in handles]
        return sub, {"items": bad}
    if cmd == "notifications":
        deadline = asyncio.get_running_loop().time() + c.get("timeout", 10)
        while len(handler.changes) < c.get("count", 0):
            left = deadline - asyncio.get_running_loop().time()
            if left <= 0:
                break
            handler.event.clear()
            try:
                await asyncio.wait_for(handler.event.wait(), left)
            except asyncio.TimeoutError:
                break
        out, handler.changes = handler.changes, []
        return {"changes": out}
    if cmd == "flood":
        return await flood(c["url"], c["sessions"])
    if cmd == "many_items":
        sub = await client.create_subscription(c.get("interval", 100), handler)
        counts = {}
        left = c["count"]
        while left > 0:
            n = min(left, c.get("chunk", 1000))
            left -= n
            try:
                handles = await sub._subscribe(
                    [node(c["id"])] * n, ua.AttributeIds.Value, queuesize=1,
                    sampling_interval=c.get("interval", 100),
                )
                names = [status_name(h) if isinstance(h, ua.StatusCode) else "Good" for h in handles]
            except ua.UaStatusCodeError as e:
                names = [status_name(e.code)] * n
            for name in names:
                counts[name] = counts.get(name, 0) + 1
        KEEP.append(sub)
        return {"items": counts}
    if cmd == "close":
        return {}
    return {"error": f"unknown command {cmd}"}


if __name__ == "__main__":
    asyncio.run(run(json.loads(sys.argv[1])))
