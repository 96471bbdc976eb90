"""Bit lengths of classic CAN frames: the frame budget of a CAN bus.

A frame occupies ``frame_bits`` bit times: start of frame, identifier, control
field, data and CRC-15 with bit stuffing (a complementary bit after five equal
ones), then CRC delimiter, ACK, end of frame and intermission. At 1 Mbit/s an
eight-byte frame takes ≈115-135 µs, so a bus carries about 8,500 of them per
second.
"""

from __future__ import annotations

import functools

import can

TAIL_BITS = 1 + 2 + 7 + 3  # CRC delimiter, ACK slot + delimiter, EOF, intermission


def _crc15_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = ((crc << 1) ^ 0x4599) if crc & 0x4000 else crc << 1
            crc &= 0x7FFF
        table.append(crc)
    return tuple(table)


_CRC15 = _crc15_table()


def _stuff_step(state: int, bit: int) -> tuple[int, int]:
    """Bit stuffing as a state machine: ``state = 4 * last bit + (run length - 1)``, runs of 1..4."""
    last, run = divmod(state, 4)
    run = run + 2 if bit == last else 1
    if run == 5:                                      # a complementary stuff bit starts a new run
        return 4 * (1 - bit), 1
    return 4 * bit + run - 1, 0


def _stuff_tables():
    bit_table = tuple(tuple(_stuff_step(state, b) for b in (0, 1)) for state in range(8))
    byte_table = []
    for state in range(8):
        row = []
        for byte in range(256):
            st, n = state, 0
            for i in range(7, -1, -1):
                st, k = bit_table[st][(byte >> i) & 1]
                n += k
            row.append((st, n))
        byte_table.append(tuple(row))
    return bit_table, tuple(byte_table)


_STUFF_BIT, _STUFF_BYTE = _stuff_tables()


def _crc_bit(crc: int, bit: int) -> int:
    return ((crc << 1) ^ 0x4599 if bit ^ (crc >> 14) else crc << 1) & 0x7FFF


@functools.lru_cache(maxsize=4096)
def _header(can_id: int, dlc: int, extended: bool, remote: bool) -> tuple[int, int, int, int]:
    """CRC, stuffing state, stuff bits so far and bit count after start of frame,
    arbitration and control fields (they repeat: computed once per identifier)."""
    if extended:
        value = ((can_id >> 18) & 0x7FF) << 2 | 0b11                  # base id, SRR, IDE
        value = (value << 18 | (can_id & 0x3FFFF)) << 3 | (4 if remote else 0)   # id extension, RTR, r1, r0
        nbits = 11 + 2 + 18 + 3
    else:
        value = (can_id & 0x7FF) << 3 | (4 if remote else 0)           # id, RTR, IDE, r0
        nbits = 11 + 3
    value = value << 4 | (dlc & 0xF)
    nbits += 4
    crc = _crc_bit(0, 0)                              # the start of frame, a 0
    state = 0                                         # after the start of frame: one 0
    stuffed = 0
    for i in range(nbits - 1, -1, -1):
        bit = (value >> i) & 1
        crc = _crc_bit(crc, bit)
        state, n = _STUFF_BIT[state][bit]
        stuffed += n
    return crc, state, stuffed, 1 + nbits


def frame_bits(can_id: int, dlc: int, data: bytes = b"", *, extended: bool = False, remote: bool = False) -> int:
    """Bits a classic CAN frame occupies on the bus, stuff bits and intermission included."""
    crc, state, stuffed, nbits = _header(can_id, dlc, extended, remote)
    if not remote:
        payload = bytes(data[:dlc])
        nbits += 8 * len(payload)
        table, stuff = _CRC15, _STUFF_BYTE
        for byte in payload:                          # CRC and stuffing a byte at a time
            crc = ((crc << 8) & 0x7FFF) ^ table[((crc >> 7) ^ byte) & 0xFF]
            state, n = stuff[state][byte]
            stuffed += n
    # bit stuffing runs on through the 15 CRC bits: the top 7 one at a time, then a byte
    for i in range(14, 7, -1):
        state, n = _STUFF_BIT[state][(crc >> i) & 1]
        stuffed += n
    stuffed += _STUFF_BYTE[state][crc & 0xFF][1]
    return nbits + 15 + stuffed + TAIL_BITS


def worst_frame_bits(dlc: int, *, extended: bool = False) -> int:
    """Upper bound of :func:`frame_bits` for any id and data of length ``dlc``."""
    stuffed_region = (39 if extended else 19) + 8 * dlc + 15
    return stuffed_region + (stuffed_region - 1) // 4 + TAIL_BITS


def message_bits(msg: can.Message) -> int:
    return frame_bits(msg.arbitration_id, msg.dlc, msg.data, extended=msg.is_extended_id,
                      remote=msg.is_remote_frame)


