#!/usr/bin/python3
"""A pymodbus master (a Modbus implementation we did not write) for hwgw's server tests,
driven by JSON lines: one request a line on stdin, one result a line on stdout.

Usage: pymodbus_client.py tcp PORT
       pymodbus_client.py rtu_over_tcp PORT      (RTU frames on TCP: pymodbus's RTU framer)
       pymodbus_client.py serial DEVICE BAUD PARITY   (RTU on a serial port; N, E or O)

Requests: {"fn": 1|2|3|4, "unit": U, "address": A, "count": N}
          {"fn": 5, "unit": U, "address": A, "value": true}
          {"fn": 6, "unit": U, "address": A, "value": 123}
          {"fn": 15, "unit": U, "address": A, "values": [true, false]}
          {"fn": 16, "unit": U, "address": A, "values": [1, 2]}
          {"raw": "hex"}  (bytes sent as they are, nothing read: a broken frame)
Results:  {"ok": [values]} (reads: registers or bits; writes: []), {"exception": code},
          {"broadcast": true} (unit 0: nothing awaited), {"error": "no reply"} or another
          error text. First line: {"ready": true} once connected.

Debian's python3-pymodbus (3.0) runs under Debian's /usr/bin/python3.
"""
import json
import sys

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.pdu import ExceptionResponse
from pymodbus.transaction import ModbusRtuFramer

TIMEOUT = 2.0

mode = sys.argv[1]
if mode == "tcp":
    client = ModbusTcpClient("127.0.0.1", port=int(sys.argv[2]), timeout=TIMEOUT, retries=0)
elif mode == "rtu_over_tcp":
    client = ModbusTcpClient("127.0.0.1", port=int(sys.argv[2]), framer=ModbusRtuFramer,
                             timeout=TIMEOUT, retries=0)
else:
    client = ModbusSerialClient(port=sys.argv[2], framer=ModbusRtuFramer, baudrate=int(sys.argv[3]),
                                parity=sys.argv[4], stopbits=1, bytesize=8, timeout=TIMEOUT, retries=0,
                                broadcast_enable=True)
if not client.connect():
    print(json.dumps({"error": "cannot connect"}), flush=True)
    sys.exit(1)
print(json.dumps({"ready": True}), flush=True)


def run(req):
    if "raw" in req:
        data = bytes.fromhex(req["raw"])
        if mode == "serial":
            client.socket.write(data)
        else:
            client.socket.send(data)
        return {"ok": []}
    fn, unit, address = req["fn"], req.get("unit", 1), req["address"]
    if fn == 1:
        r = client.read_coils(address, req["count"], slave=unit)
    elif fn == 2:
        r = client.read_discrete_inputs(address, req["count"], slave=unit)
    elif fn == 3:
        r = client.read_holding_registers(address, req["count"], slave=unit)
    elif fn == 4:
        r = client.read_input_registers(address, req["count"], slave=unit)
    elif fn == 5:
        r = client.write_coil(address, req["value"], slave=unit)
    elif fn == 6:
        r = client.write_register(address, req["value"], slave=unit)
    elif fn == 15:
        r = client.write_coils(address, req["values"], slave=unit)
    elif fn == 16:
        r = client.write_registers(address, req["values"], slave=unit)
    else:
        return {"error": "unknown fn %r" % fn}
    if unit == 0 and mode == "serial":
        return {"broadcast": True}
    if isinstance(r, ExceptionResponse):
        return {"exception": r.exception_code}
    if r.isError():
        return {"error": "no reply" if "No response" in str(r) or "no response" in str(r).lower() else str(r)}
    if fn in (1, 2):
        return {"ok": [bool(b) for b in r.bits[:req["count"]]]}
    if fn in (3, 4):
        return {"ok": list(r.registers)}
    return {"ok": []}


for line in sys.stdin:
    try:
        print(json.dumps(run(json.loads(line))), flush=True)
    except Exception as e:  # every request gets a line: the test judges it
        print(json.dumps({"error": "%s: %s" % (type(e).__name__, e)}), flush=True)
