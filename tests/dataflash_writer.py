"""A small ArduPilot DataFlash (.bin) writer for tests: FMT definitions, then messages, in the
binary layout pymavlink's DFReader reads (0xA3 0x95, message id, little-endian payload).

Format characters and the scale pymavlink divides by on reading (so a value is written as
value × scale): c/C/e/E ×100, L ×1e7; n/N/Z are 4/16/64-byte strings.
"""

from __future__ import annotations

import struct

HEAD = b"\xa3\x95"
FMT_ID = 128
PACK = {"b": "b", "B": "B", "h": "h", "H": "H", "i": "i", "I": "I", "f": "f", "d": "d", "n": "4s", "N": "16s",
        "Z": "64s", "c": "h", "C": "H", "e": "i", "E": "I", "L": "i", "M": "B", "q": "q", "Q": "Q"}
SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}


class DataFlashWriter:
    def __init__(self):
        self.data = bytearray()
        self.defs: dict[str, tuple[int, str, struct.Struct]] = {}
        self._define(FMT_ID, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns")

    def _define(self, msg_id: int, name: str, fmt: str, columns: str) -> None:
        st = struct.Struct("<" + "".join(PACK[c] for c in fmt))
        self.defs[name] = (msg_id, fmt, st)
        self.write("FMT", msg_id, st.size + 3, name, fmt, columns)

    def define(self, name: str, fmt: str, columns: str) -> None:
        self._define(FMT_ID + len(self.defs), name, fmt, columns)

    def write(self, name: str, *values) -> None:
        msg_id, fmt, st = self.defs[name]
        packed = []
        for c, v in zip(fmt, values):
            if c in "nNZ":
                packed.append(v.encode() if isinstance(v, str) else v)
            elif c in SCALE:
                packed.append(int(round(v * SCALE[c])))
            elif c in "fd":
                packed.append(float(v))
            else:
                packed.append(int(round(v)))
        self.data += HEAD + bytes([msg_id]) + st.pack(*packed)

    def save(self, path) -> None:
        with open(path, "wb") as fh:
            fh.write(bytes(self.data))


# the messages an ArduCopter 4.x log holds that magcal reads, in the firmware's layouts
AP4_MESSAGES = (
    ("PARM", "QNff", "TimeUS,Name,Value,Default"),
    ("MSG", "QZ", "TimeUS,Message"),
    ("MAG", "QBhhhhhhhhhBI", "TimeUS,I,MagX,MagY,MagZ,OfsX,OfsY,OfsZ,MOX,MOY,MOZ,Health,S"),
    ("ATT", "QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
    ("GPS", "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    ("BAT", "QBfffffcfBBB", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct,H,SH"),
)


def ap4_writer() -> DataFlashWriter:
    """A writer with the ArduCopter 4.x messages defined."""
    w = DataFlashWriter()
    for name, fmt, columns in AP4_MESSAGES:
        w.define(name, fmt, columns)
    return w
