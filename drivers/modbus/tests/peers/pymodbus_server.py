#!/usr/bin/python3
"""Starts a pymodbus server (a third-party Modbus implementation) for hwgw's tests.

Usage: pymodbus_server.py tcp PORT
       pymodbus_server.py rtu DEVICE
       pymodbus_server.py sparse PORT
       pymodbus_server.py pattern_rtu_over_tcp PORT
       pymodbus_server.py pattern_tcp PORT

sparse: input registers only at 0-9, 20-29 and 100-109 (register n holds 1000 + n); a
read that touches any other address is refused with IllegalDataAddress, as devices with
holes in their map do.

Its registers hold known values the tests decode; on RTU, units 1 and 2 share the line
with different contents (multi-drop). pattern_rtu_over_tcp: RTU frames on TCP (as a serial device server carries them), any
unit id, 2000 addresses (pattern_tcp: the same over Modbus TCP) in every table holding a pattern the tests compute alike
(testkit::pymodbus::pattern): input register n = (n * 0x9E37 + 0x1234) mod 2^16, holding
register n = (n * 0x6C8B + 0x4321) mod 2^16, discrete input n = (n * 7) mod 3 == 0, coil
n = (n * 5) mod 4 == 1.

It serves until killed. Debian's
python3-pymodbus (3.0) runs under Debian's /usr/bin/python3.
"""
import sys

from pymodbus.datastore import ModbusSequentialDataBlock, ModbusServerContext, ModbusSlaveContext
from pymodbus.server import StartSerialServer, StartTcpServer
from pymodbus.transaction import ModbusRtuFramer

ir = [0] * 100
hr = [0] * 100
di = [False] * 100
co = [False] * 100
ir[0] = (-123) & 0xFFFF          # i16, scale 0.1: -12.3
ir[1], ir[2] = 0x40C8, 0x0000    # f32: 6.25
hr[20], hr[21] = 0x0001, 0x0002  # u32: 65538
di[3] = True
ir[10] = 40000                                   # u16
ir[11], ir[12] = 0xFFFE, 0xEE90                  # i32: -70000
ir[20:24] = [0x0001, 0x0002, 0x0003, 0x0004]     # u64: 0x0001000200030004
ir[24:28] = [0xFFFF, 0xFFFF, 0xFFFF, 0xFFFB]     # i64: -5
ir[30:34] = [0x3FF4, 0x0000, 0x0000, 0x0000]     # f64: 1.25
ir[40] = 0b1000_0000_0000_0010                   # bits 1 and 15 set
ir[50:52] = [0x4640, 0xE6B6]                     # f32: 12345.678 (f32 12345.677734375)
ir[52:54] = [0x7FC0, 0x0000]                     # f32: NaN
ir[54:56] = [0x39D1, 0xB717]                     # f32: 0.0004
ir[56:58] = [0xFF80, 0x0000]                     # f32: -inf
hr[40] = 1234                                    # an output the device already holds
co[8] = True                                     # a coil already on

store = ModbusSlaveContext(
    di=ModbusSequentialDataBlock(0, di),
    co=ModbusSequentialDataBlock(0, co),
    hr=ModbusSequentialDataBlock(0, hr),
    ir=ModbusSequentialDataBlock(0, ir),
    zero_mode=True,  # address n is register n, as on the wire
)

if sys.argv[1] in ("pattern_rtu_over_tcp", "pattern_tcp"):
    n = range(2000)
    pattern = ModbusSlaveContext(
        di=ModbusSequentialDataBlock(0, [(a * 7) % 3 == 0 for a in n]),
        co=ModbusSequentialDataBlock(0, [(a * 5) % 4 == 1 for a in n]),
        hr=ModbusSequentialDataBlock(0, [(a * 0x6C8B + 0x4321) & 0xFFFF for a in n]),
        ir=ModbusSequentialDataBlock(0, [(a * 0x9E37 + 0x1234) & 0xFFFF for a in n]),
        zero_mode=True,
    )
    StartTcpServer(
        context=ModbusServerContext(slaves=pattern, single=True),
        address=("127.0.0.1", int(sys.argv[2])),
        **({"framer": ModbusRtuFramer} if sys.argv[1] == "pattern_rtu_over_tcp" else {}),
    )
elif sys.argv[1] == "sparse":
    from pymodbus.datastore import ModbusSparseDataBlock
    regs = {a: 1000 + a for a in list(range(0, 10)) + list(range(20, 30)) + list(range(100, 110))}
    sparse = ModbusSlaveContext(
        di=ModbusSparseDataBlock({0: False}),
        co=ModbusSparseDataBlock({0: False}),
        hr=ModbusSparseDataBlock({0: 0}),
        ir=ModbusSparseDataBlock(regs),
        zero_mode=True,
    )
    StartTcpServer(context=ModbusServerContext(slaves=sparse, single=True), address=("127.0.0.1", int(sys.argv[2])))
elif sys.argv[1] == "tcp":
    # Any unit id reaches the one store.
    StartTcpServer(context=ModbusServerContext(slaves=store, single=True), address=("127.0.0.1", int(sys.argv[2])))
else:
    # Multi-drop: units 1 and 2 on one line, with different contents.
    ir2 = [0] * 100
    ir2[0] = 77
    store2 = ModbusSlaveContext(
        di=ModbusSequentialDataBlock(0, [False] * 100),
        co=ModbusSequentialDataBlock(0, [False] * 100),
        hr=ModbusSequentialDataBlock(0, [0] * 100),
        ir=ModbusSequentialDataBlock(0, ir2),
        zero_mode=True,
    )
    context = ModbusServerContext(slaves={1: store, 2: store2}, single=False)
    StartSerialServer(context=context, framer=ModbusRtuFramer, port=sys.argv[2], baudrate=19200, timeout=0.05)
