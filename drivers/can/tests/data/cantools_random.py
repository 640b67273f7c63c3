"""Random DBC files written by cantools, and frames decoded by cantools: the independent
reference `drivers/can/tests/cantools.rs` compares hwgw's DBC reader and decoding with.

    python3 cantools_random.py OUT_DIR SEED FILES FRAMES

Writes OUT_DIR/dbc_N.dbc (cantools' DBC writer, Windows-1252 as CANdb++ writes) and
OUT_DIR/expected.json: for each file its messages (cycle time, signals with their
comments and value tables) and FRAMES random frames per message, each with cantools'
decoding (raw and scaled, values as Python's repr so floats and big integers survive).
"""

import json
import math
import os
import random
import struct
import sys

import cantools
from cantools.database.can import Database, Message, Node, Signal
from cantools.database.conversion import BaseConversion

# Names repeat across messages, as Counter and CRC do in real files.
NAMES = ["Counter", "CRC", "Speed", "Temp", "Status", "Mode", "Level", "Pressure",
         "Torque", "Voltage", "Current", "Flags", "Gear", "Angle", "Rate", "Alive"]
UNITS = ["", "", "\u00b0C", "km/h", "%", "\u00b5s", "bar", "V", "A", "\u20ac"]
SCALES = [1, 1, 1, 0.1, 0.01, 0.5, 0.25, 0.0625, 3, 0.001, 1e-05, 2.5]
OFFSETS = [0, 0, 0, -40, 100, -0.5, 1000, -273.15]


def number(rng, pool):
    """A factor or offset: mostly a round one, sometimes an arbitrary decimal."""
    if rng.random() < 0.2:
        return float("%.6g" % rng.uniform(-100, 100)) or 1.0
    return rng.choice(pool)


def candidate(rng, name, length_bytes, mux_ids=None, mux_name=None):
    """One random signal that may or may not fit the message."""
    bits = 8 * length_bytes
    kind = rng.random()
    is_float = False
    if kind < 0.08 and bits >= 32:
        length, is_float = 32, True
    elif kind < 0.12 and bits >= 64:
        length, is_float = 64, True
    elif kind < 0.18 and bits >= 64:
        length = 64
    elif kind < 0.35:
        length = 1
    elif kind < 0.5:
        length = rng.randint(2, min(64, bits))
    else:
        length = rng.randint(2, min(32, bits))
    byte_order = rng.choice(["little_endian", "big_endian"])
    if length == 64 and rng.random() < 0.5:
        start = 0 if byte_order == "little_endian" else 7
    else:
        start = rng.randrange(bits)
    signed = (not is_float) and length > 1 and rng.random() < 0.4
    scale = 1 if length == 1 else number(rng, SCALES)
    offset = 0 if length == 1 else number(rng, OFFSETS)
    choices = None
    if not is_float and length <= 16 and rng.random() < 0.3:
        top = (1 << length) - 1
        keys = sorted(set(rng.randint(0, min(top, 20)) for _ in range(rng.randint(1, 4))))
        choices = {k: "state %d \u00e4" % k if rng.random() < 0.3 else "S%d" % k for k in keys}
    # Limits as CANdb++ writes them: the raw type's whole range, scaled.
    minimum = maximum = None
    if not is_float and rng.random() < 0.3:
        lo = -(1 << (length - 1)) if signed else 0
        hi = (1 << (length - 1)) - 1 if signed else (1 << length) - 1
        ends = sorted([lo * scale + offset, hi * scale + offset])
        minimum, maximum = ends
    comment = None
    if rng.random() < 0.3:
        comment = rng.choice(["Measured at the sump, \u00b0C", "Two\nlines", "Plain"])
    return Signal(
        name=name,
        start=start,
        length=length,
        byte_order=byte_order,
        is_signed=signed,
        conversion=BaseConversion.factory(scale=scale, offset=offset, choices=choices,
                                          is_float=is_float),
        unit=rng.choice(UNITS),
        minimum=minimum,
        maximum=maximum,
        comment=comment,
        receivers=["GW"],
        multiplexer_ids=mux_ids,
        multiplexer_signal=mux_name,
    )


def fits(frame_id, name, length, signals, extended, fd):
    try:
        Message(frame_id=frame_id, name=name, length=length, signals=signals,
                is_extended_frame=extended, is_fd=fd, strict=True)
        return True
    except Exception:
        return False


def message(rng, frame_id, name, extended):
    fd = rng.random() < 0.15
    length = rng.choice([12, 16, 20, 24, 32, 48, 64] if fd else [1, 2, 4, 6, 8, 8, 8])
    signals = []
    used = set()
    mux_ids = None
    if length >= 2 and rng.random() < 0.25:
        mux = Signal(name="Page", start=0, length=rng.choice([2, 4, 8]), is_multiplexer=True,
                     receivers=["GW"])
        signals.append(mux)
        used.add("Page")
        mux_ids = sorted(rng.sample(range(1 << min(mux.length, 3)), 2))
    for _ in range(rng.randint(1, 10)):
        sname = rng.choice(NAMES)
        if sname in used:
            continue
        ids = None
        if mux_ids is not None and rng.random() < 0.6:
            ids = [rng.choice(mux_ids)]
        s = candidate(rng, sname, length, ids, "Page" if ids else None)
        if fits(frame_id, name, length, signals + [s], extended, fd):
            signals.append(s)
            used.add(sname)
    if not any(not s.is_multiplexer for s in signals):
        return None
    cycle = rng.choice([None, None, 10, 100, 1000])
    return Message(frame_id=frame_id, name=name, length=length, signals=signals,
                   is_extended_frame=extended, is_fd=fd, senders=["ECU"], cycle_time=cycle,
                   comment=rng.choice([None, "Sent by the ECU, \u00b0C"]), strict=True)


def random_raw(rng, s):
    """A raw value of signal `s`: any bit pattern (a float's may be NaN or infinite)."""
    if s.is_float:
        fmt = "<f" if s.length == 32 else "<d"
        return struct.unpack(fmt, bytes(rng.getrandbits(8) for _ in range(s.length // 8)))[0]
    lo = -(1 << (s.length - 1)) if s.is_signed else 0
    hi = (1 << (s.length - 1)) - 1 if s.is_signed else (1 << s.length) - 1
    return rng.randint(lo, hi)


def double_reach(s):
    """The raw magnitude a double signal's scale in hwgw reaches (see Signal::with_kind)."""
    k = max(0, math.ceil(math.log2(abs(s.scale)))) if s.scale else 0
    return 2.0 ** (1023 - k)


def payload(rng, msg):
    """Random bytes; a multiplexed message's selector set to one of its values first."""
    mux = [s for s in msg.signals if s.is_multiplexer]
    ids = sorted({i for s in msg.signals for i in (s.multiplexer_ids or [])})
    if not mux or not ids:
        return bytes(rng.getrandbits(8) for _ in range(msg.length))
    page = rng.choice(ids)
    values = {mux[0].name: page}
    for s in msg.signals:
        if not s.is_multiplexer and (not s.multiplexer_ids or page in s.multiplexer_ids):
            values[s.name] = random_raw(rng, s)
    return msg.encode(values, scaling=False, padding=True, strict=False)


def main():
    out, seed, files, frames = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    rng = random.Random(seed)
    expected = []
    for n in range(files):
        messages = []
        ids = set()
        for m in range(rng.randint(1, 6)):
            extended = rng.random() < 0.3
            frame_id = rng.randrange(1 << 29) if extended else rng.randrange(0x800)
            if frame_id in ids:
                continue
            msg = message(rng, frame_id, "Msg%d_%d" % (n, m), extended)
            if msg is not None:
                ids.add(frame_id)
                messages.append(msg)
        if not messages:
            continue
        db = Database(messages=messages, nodes=[Node("ECU"), Node("GW")])
        path = os.path.join(out, "dbc_%d.dbc" % n)
        cantools.database.dump_file(db, path, encoding="cp1252")
        # Read back as any user would: what the file says, not what was built.
        db = cantools.database.load_file(path, encoding="cp1252")
        entry = {"file": os.path.basename(path), "messages": []}
        for msg in db.messages:
            signals = {}
            for s in msg.signals:
                comment = s.comment if isinstance(s.comment, str) else None
                choices = {str(int(k)): str(v) for k, v in (s.choices or {}).items()}
                signals[s.name] = {"comment": comment, "choices": choices,
                                   "multiplexer": s.is_multiplexer}
            decoded = []
            sent = []
            for _ in range(frames):
                data = payload(rng, msg)
                raw = msg.decode(data, decode_choices=False, scaling=False)
                scaled = msg.decode(data, decode_choices=False, scaling=True)
                decoded.append({"data": data.hex(),
                                "values": {k: [repr(raw[k]), repr(scaled[k])] for k in scaled}})
                # The same values sent: cantools' encoding of them, unused bits 0. A
                # multiplexed message is received only; NaN and infinities are not written.
                finite = all(not isinstance(v, float) or v == v and abs(v) != float("inf")
                             for v in scaled.values())
                # hwgw's double outputs reach 2^1023 (half the type's largest value), less
                # by the factor's power of two.
                finite = finite and all(abs(raw.get(s.name, 0.0)) < double_reach(s)
                                        for s in msg.signals if s.is_float)
                # Values as an f64 carries them (hwgw's outputs take f64).
                if not msg.is_multiplexed() and finite:
                    as_f64 = {k: float(v) for k, v in scaled.items()}
                    out_data = msg.encode(as_f64, scaling=True, padding=False, strict=False)
                    sent.append({"data": out_data.hex(),
                                 "values": {k: [repr(raw[k]), repr(as_f64[k])]
                                            for k in scaled}})
            entry["messages"].append({"name": msg.name, "id": msg.frame_id,
                                      "extended": msg.is_extended_frame,
                                      "fd": msg.is_fd,
                                      "cycle_ms": msg.cycle_time, "signals": signals,
                                      "frames": decoded, "sent": sent})
        expected.append(entry)
    with open(os.path.join(out, "expected.json"), "w", encoding="utf-8") as f:
        json.dump(expected, f)


if __name__ == "__main__":
    main()
