"""Bit lengths of classic CAN frames: the frame budget of a CAN bus.

A frame occupies ``frame_bits`` bit times: start of frame, identifier, control
field, data and CRC-15 with bit stuffing (a complementary bit after five equal
ones), then CRC delimiter, ACK, end of frame and intermission. At 1 Mbit/s an
eight-byte frame takes ≈115-135 µs, so a bus carries about 8,500 of them per
second.
"""

from __future__ import annotations

import can

SYNC_COB_ID = 0x80
#: function codes (COB-ID >> 7) of the four TPDOs
TPDO_FUNCTIONS = (0x3, 0x5, 0x7, 0x9)
TAIL_BITS = 1 + 2 + 7 + 3  # CRC delimiter, ACK slot + delimiter, EOF, intermission


def _crc15(bits: list[int]) -> int:
    crc = 0
    for b in bits:
        nxt = b ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if nxt:
            crc ^= 0x4599
    return crc


def frame_bits(can_id: int, dlc: int, data: bytes = b"", *, extended: bool = False, remote: bool = False) -> int:
    """Bits a classic CAN frame occupies on the bus, stuff bits and intermission included."""
    bits: list[int] = [0]  # SOF
    if extended:
        bits += [(can_id >> (28 - i)) & 1 for i in range(11)]        # base id
        bits += [1, 1]                                               # SRR, IDE
        bits += [(can_id >> (17 - i)) & 1 for i in range(18)]        # id extension
        bits += [1 if remote else 0, 0, 0]                           # RTR, r1, r0
    else:
        bits += [(can_id >> (10 - i)) & 1 for i in range(11)]
        bits += [1 if remote else 0, 0, 0]                           # RTR, IDE, r0
    bits += [(dlc >> (3 - i)) & 1 for i in range(4)]
    if not remote:
        for byte in bytes(data)[:dlc]:
            bits += [(byte >> (7 - i)) & 1 for i in range(8)]
    crc = _crc15(bits)
    bits += [(crc >> (14 - i)) & 1 for i in range(15)]
    stuffed = 0
    run_bit, run_len = bits[0], 1
    for b in bits[1:]:
        if b == run_bit:
            run_len += 1
            if run_len == 5:
                stuffed += 1
                run_bit, run_len = 1 - b, 1   # the stuff bit starts a new run
        else:
            run_bit, run_len = b, 1
    return len(bits) + stuffed + TAIL_BITS


def worst_frame_bits(dlc: int, *, extended: bool = False) -> int:
    """Upper bound of :func:`frame_bits` for any id and data of length ``dlc``."""
    stuffed_region = (39 if extended else 19) + 8 * dlc + 15
    return stuffed_region + (stuffed_region - 1) // 4 + TAIL_BITS


def message_bits(msg: can.Message) -> int:
    return frame_bits(msg.arbitration_id, msg.dlc, bytes(msg.data), extended=msg.is_extended_id,
                      remote=msg.is_remote_frame)


